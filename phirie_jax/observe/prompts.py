"""Prompts: the user points at an object in one photo, the pipeline does the rest.

A prompt is one object, given as

- a box around it, ``IMAGE:X0,Y0,X1,Y1``, or
- a click on it, ``IMAGE:U,V``,

in the pixel coordinates any image viewer shows: (0, 0) is the top-left corner of the photo,
x to the right, y down, pixel (i, j) covers [i, i + 1) × [j, j + 1) (so pixel centres are at
i + 0.5, the cameras' own convention, docs/architecture.md "Contracts"). ``IMAGE`` is the photo's name as
the cameras list it (``0007.jpg``) or its stem (``0007``). An optional ``=LABEL`` at the end
(``0007.jpg:120,80,260,240=mug``) gives the object a category.

The same prompts can live in the scene folder as ``prompts.json``::

    {"prompts": [{"image": "0007.jpg", "box": [x0, y0, x1, y1], "label": "mug"},
                 {"image": "0012.jpg", "point": [u, v]}]}

Prompt k (1-based, in the order given) becomes instance k. Everything here is checked before
any work: a malformed prompt, an image no camera shows, a box or click outside its photo are
one line naming the option (or the file and the field) and what was expected.
``observe.prompt_lift`` turns checked prompts into per-view instance masks.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Sequence
from pathlib import Path

from phirie_jax.errors import OptionError, SceneInputError
from phirie_jax.types import Camera

PROMPTS_FILE = "prompts.json"
OPTION = "--prompt"
LISTED_NAMES = 5          # an unknown image's message lists this many of the cameras' names
KEYS = ("image", "box", "point", "label")


@dataclasses.dataclass(frozen=True)
class Prompt:
    """One object pointed at in one photo (image-viewer pixel coordinates, module docstring).

    Exactly one of ``box`` (x0, y0, x1, y1 with x0 < x1, y0 < y1) and ``point`` (u, v) is set.
    ``origin`` says where it was given, for messages: ``--prompt`` or ``prompts.json[k]``."""

    image: str
    box: tuple[float, float, float, float] | None = None
    point: tuple[float, float] | None = None
    label: str | None = None
    origin: str = OPTION

    def __post_init__(self):
        if (self.box is None) == (self.point is None):
            both = "both" if self.box is not None else "neither"
            raise ValueError(f"prompt on {self.image!r}: expected a box or a point, not {both}")

    @property
    def kind(self) -> str:
        return "box" if self.box is not None else "point"

    def as_json(self) -> dict:
        """The entry ``prompts.json`` holds for it."""
        out: dict = {"image": self.image}
        if self.box is not None:
            out["box"] = [_plain_number(v) for v in self.box]
        else:
            out["point"] = [_plain_number(v) for v in self.point]
        if self.label:
            out["label"] = self.label
        return out

    def as_text(self) -> str:
        """The ``--prompt`` value that gives it."""
        values = self.box if self.box is not None else self.point
        text = f"{self.image}:{','.join(str(_plain_number(v)) for v in values)}"
        return text + (f"={self.label}" if self.label else "")


def _plain_number(value: float) -> float | int:
    return int(value) if float(value).is_integer() else float(value)


# --- parsing -------------------------------------------------------------------------------


def parse_prompt(text: str) -> Prompt:
    """A ``--prompt`` value (``IMAGE:X0,Y0,X1,Y1`` or ``IMAGE:U,V``, optionally ``=LABEL``);
    ``OptionError`` when it is malformed. The image is checked later (``check_prompts``)."""
    expected = "expected IMAGE:X0,Y0,X1,Y1 (a box) or IMAGE:U,V (a click), e.g. 0007.jpg:120,80,260,240"
    body, _, label = text.partition("=")
    image, colon, numbers = body.rpartition(":")
    if not colon or not image.strip():
        raise OptionError(OPTION, expected, repr(text))
    try:
        values = [float(v) for v in numbers.split(",")]
    except ValueError:
        raise OptionError(OPTION, f"{numbers!r} are not numbers ({expected})", repr(text)) from None
    if len(values) not in (2, 4):
        raise OptionError(OPTION, f"{len(values)} numbers ({expected})", repr(text))
    if not all(math.isfinite(v) for v in values):
        raise OptionError(OPTION, f"non-finite coordinates ({expected})", repr(text))
    label = label.strip() or None
    if len(values) == 2:
        return Prompt(image.strip(), point=(values[0], values[1]), label=label)
    x0, y0, x1, y1 = values
    return Prompt(image.strip(), box=(min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1)), label=label)


def _number_list(value, count: int) -> list[float] | None:
    if not isinstance(value, list) or len(value) != count:
        return None
    if any(isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) for v in value):
        return None
    return [float(v) for v in value]


def prompts_from_json(data, path: Path) -> list[Prompt]:
    """The prompts of a parsed ``prompts.json`` (module docstring); ``SceneInputError`` naming the
    file and the field for anything else."""
    if not isinstance(data, dict) or not isinstance(data.get("prompts"), list):
        raise SceneInputError(path, "prompts", 'expected {"prompts": [{"image": ..., "box": [x0, y0, x1, y1]} '
                              'or {"image": ..., "point": [u, v]}, ...]}')
    out = []
    for k, item in enumerate(data["prompts"]):
        field = f"prompts[{k}]"
        if not isinstance(item, dict):
            raise SceneInputError(path, field, f"{item!r} (expected an object with image and box or point)")
        unknown = sorted(set(item) - set(KEYS))
        if unknown:
            raise SceneInputError(path, f"{field}.{unknown[0]}", f"unknown key (expected {', '.join(KEYS)})")
        image = item.get("image")
        if not isinstance(image, str) or not image.strip():
            raise SceneInputError(path, f"{field}.image", f"{image!r} (expected an image name such as 0007.jpg)")
        if ("box" in item) == ("point" in item):
            raise SceneInputError(path, field, "expected exactly one of box [x0, y0, x1, y1] and point [u, v]")
        label = item.get("label")
        if label is not None and (not isinstance(label, str) or not label.strip()):
            raise SceneInputError(path, f"{field}.label", f"{label!r} (expected a non-empty string)")
        label = label.strip() if label else None
        origin = f"{path.name}[{k}]"
        if "box" in item:
            box = _number_list(item["box"], 4)
            if box is None:
                raise SceneInputError(path, f"{field}.box",
                                      f"{item['box']!r} (expected [x0, y0, x1, y1], four numbers)")
            x0, y0, x1, y1 = box
            out.append(Prompt(image.strip(), box=(min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1)),
                              label=label, origin=origin))
        else:
            point = _number_list(item["point"], 2)
            if point is None:
                raise SceneInputError(path, f"{field}.point", f"{item['point']!r} (expected [u, v], two numbers)")
            out.append(Prompt(image.strip(), point=(point[0], point[1]), label=label, origin=origin))
    return out


def read_prompts_file(path: str | Path) -> list[Prompt]:
    """The prompts of a ``prompts.json`` file (``SceneInputError`` naming the file and field)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise SceneInputError(path, None, f"not valid JSON ({err})") from None
    return prompts_from_json(data, path)


# --- checking against the cameras ---------------------------------------------------------


def camera_for(image: str, cameras: Sequence[Camera]) -> int | None:
    """Index of the camera whose image is ``image`` (its name, its file name or its stem), or None;
    ``ValueError`` when a stem names several."""
    names = [c.name for c in cameras]
    if image in names:
        return names.index(image)
    for key in (lambda n: Path(n).name, lambda n: Path(n).stem):
        found = [k for k, n in enumerate(names) if key(n) == image]
        if len(found) > 1:
            raise ValueError(f"image {image!r} names {len(found)} cameras ({', '.join(names[k] for k in found[:3])}): "
                             "give the full name")
        if found:
            return found[0]
    return None


def _some_names(cameras: Sequence[Camera]) -> str:
    names = [c.name for c in cameras]
    shown = ", ".join(names[:LISTED_NAMES])
    return shown + (f", … ({len(names)} images)" if len(names) > LISTED_NAMES else "")


def prompt_problem(prompt: Prompt, cameras: Sequence[Camera]) -> tuple[int | None, str | None]:
    """(camera index, None) for a usable prompt, else (None or the index, what is wrong)."""
    try:
        view = camera_for(prompt.image, cameras)
    except ValueError as err:
        return None, str(err)
    if view is None:
        return None, f"no image {prompt.image!r} in the cameras (expected one of {_some_names(cameras)})"
    cam = cameras[view]
    if prompt.box is not None:
        x0, y0, x1, y1 = prompt.box
        if not (0 <= x0 and 0 <= y0 and x1 <= cam.width and y1 <= cam.height):
            return view, (f"box {list(map(_plain_number, prompt.box))} leaves the image {cam.name} "
                          f"(expected 0 ≤ x ≤ {cam.width}, 0 ≤ y ≤ {cam.height})")
        if x1 - x0 < 1 or y1 - y0 < 1:
            return view, f"box {list(map(_plain_number, prompt.box))} is less than a pixel wide or high"
    else:
        u, v = prompt.point
        if not (0 <= u < cam.width and 0 <= v < cam.height):
            return view, (f"point {list(map(_plain_number, prompt.point))} is outside the image {cam.name} "
                          f"(expected 0 ≤ u < {cam.width}, 0 ≤ v < {cam.height})")
    return view, None


def check_prompts(prompts: Sequence[Prompt], cameras: Sequence[Camera], path: Path | None = None
                  ) -> tuple[Prompt, ...]:
    """The prompts with their images named as the cameras name them; the first problem raised as
    an ``OptionError`` (``--prompt``) or a ``SceneInputError`` naming ``path`` (``prompts.json``)."""
    checked = []
    for k, prompt in enumerate(prompts):
        view, problem = prompt_problem(prompt, cameras)
        if problem is not None:
            if path is None:
                raise OptionError(OPTION, problem, repr(prompt.as_text()))
            raise SceneInputError(path, f"prompts[{k}]", problem)
        checked.append(dataclasses.replace(prompt, image=cameras[view].name))
    return tuple(checked)


def scene_prompts(root: Path, cameras: Sequence[Camera], given: Sequence[str | Prompt] = ()
                  ) -> tuple[tuple[Prompt, ...], Path | None]:
    """(checked prompts, the file they came from or None): the ``--prompt`` values when given,
    else the scene folder's ``prompts.json`` when it has one, else none."""
    if given:
        prompts = [p if isinstance(p, Prompt) else parse_prompt(p) for p in given]
        return check_prompts(prompts, cameras), None
    path = Path(root) / PROMPTS_FILE
    if not path.is_file():
        return (), None
    prompts = read_prompts_file(path)
    if not prompts:
        return (), path
    return check_prompts(prompts, cameras, path), path


# --- the viewer's file ----------------------------------------------------------------------


def update_prompts(path: str | Path, add: Sequence[Prompt] = (), remove: Sequence[Prompt] = ()) -> list[Prompt]:
    """Add ``add`` to the ``prompts.json`` at ``path`` (created when missing), take out the entries
    equal to one of ``remove`` (an undo), and return what the file now holds. Everything else the
    file holds — its own prompts, its other keys — is kept: a prompt is never lost by being
    written over. A file that is not a valid prompts file is left as it is (``SceneInputError``).
    Written to a temporary name and renamed (``io.atomic``)."""
    from phirie_jax.io.atomic import write_text

    path = Path(path)
    data: dict = {}
    prompts: list[Prompt] = []
    if path.exists():
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            raise SceneInputError(path, None, f"not valid JSON ({err}); left as it is") from None
        prompts = prompts_from_json(data, path)
    gone = [p.as_json() for p in remove]
    prompts = [p for p in prompts if p.as_json() not in gone]
    held = [p.as_json() for p in prompts]
    prompts += [p for p in add if p.as_json() not in held]
    data = {**data, "prompts": [p.as_json() for p in prompts]}
    write_text(path, json.dumps(data, indent=1) + "\n")
    return [dataclasses.replace(p, origin=f"{path.name}[{k}]") for k, p in enumerate(prompts)]
