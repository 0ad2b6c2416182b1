"""``manifest.json``: the versioned record every stage writes (docs/architecture.md "Contracts").

One small API for every stage: load the manifest of an output folder (or start one),
replace a section (``instances``, ``objects``, ``background``, or a stage's own
record), add items to a list section by id, record a stage's time, write atomically.

    manifest = Manifest.load_or_create(out_dir)
    with manifest.timed("observe"):
        ...
    manifest.set("instances", [...])
    manifest.write()
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import time
from collections.abc import Iterator
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np

from phirie_jax.errors import SceneInputError
from phirie_jax.io.atomic import write_text
from phirie_jax.io.jsonfile import read_json_object
from phirie_jax.layout import MANIFEST, resolve

SCHEMA = "phirie/1"

# The stages of a conversion in the order their outputs build on each other (the background keeps
# the Gaussians of an object physics fails, so it follows physics; ``pipeline.STAGES`` runs it
# first, beside the collision, and again when physics fails one), as ``stages`` records them:
# ``pending`` (this run will run it), ``running`` (started, not finished: the run was killed or still
# runs), ``complete``, ``failed`` (``failed_stage`` says why) or ``outdated`` (an earlier stage ran
# again after it).
STAGE_NAMES = ("frame", "observe", "objects", "physics", "background")
PENDING, RUNNING, COMPLETE, FAILED, OUTDATED = "pending", "running", "complete", "failed", "outdated"


class ObjectStatus(StrEnum):
    """An object's status (``objects[].status``; a ``str``, written to JSON as its value)."""

    ACCEPTED = "accepted"       # every check passed
    UNVERIFIED = "unverified"   # kept although a check failed (the reason names the checks)
    REJECTED = "rejected"       # not kept (the reason says why)
    FAILED = "failed"           # its stage failed for it (recorded)


ACCEPTED, UNVERIFIED, REJECTED, FAILED_OBJECT = ObjectStatus
KEPT = (ACCEPTED, UNVERIFIED)   # objects that are bodies of the scene


def is_kept(entry: dict) -> bool:
    """Whether an ``objects`` entry is a body of the scene (accepted or unverified)."""
    return entry.get("status") in KEPT


# The section each stage writes last (how a manifest without ``stages`` tells what ran).
LAST_WRITTEN = {"frame": "frame", "observe": "instances", "objects": "objects", "physics": "physics",
                "background": "background"}


def _plain(value: Any) -> Any:
    """NumPy scalars/arrays and paths → JSON values; non-finite floats → None."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return _plain(value.item())
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


@dataclasses.dataclass
class Elapsed:
    """Wall seconds of a finished ``Manifest.timed`` block."""

    seconds: float = 0.0


class Manifest:
    """The manifest of one output folder, held in memory until ``write``."""

    def __init__(self, out_dir: str | Path, data: dict | None = None):
        self.out_dir = Path(out_dir)
        self.data: dict = data if data is not None else {"schema": SCHEMA, "timings": {}}
        self._timed: set[str] = set()  # timings recorded by this run (later blocks add to them)

    @property
    def path(self) -> Path:
        return self.out_dir / MANIFEST

    @classmethod
    def load_or_create(cls, out_dir: str | Path) -> Manifest:
        """The folder's manifest when there is one (schema checked), else an empty one."""
        path = Path(out_dir) / MANIFEST
        if not path.exists():
            return cls(out_dir)
        data = read_json_object(path)
        if data.get("schema") != SCHEMA:
            raise SceneInputError(path, "schema", f"{data.get('schema')!r} (expected {SCHEMA!r})")
        if not isinstance(data.setdefault("timings", {}), dict):
            raise SceneInputError(path, "timings", "expected an object {stage: seconds}")
        return cls(out_dir, data)

    def get(self, section: str, default: Any = None) -> Any:
        return self.data.get(section, default)

    def require(self, section: str, written_by: str) -> Any:
        """A section earlier stages write; missing → an error naming them (``written_by``, e.g.
        "the observation stage")."""
        value = self.data.get(section)
        if value is None:
            raise SceneInputError(self.path, section, f"missing (run {written_by} first: it writes the {section})")
        return value

    # --- what earlier stages wrote: typed reads, one place that knows the sections' shapes ---

    def instances(self) -> list[dict]:
        """The observed instances (``instances``; the observation stage writes them)."""
        return self.require("instances", "the observation stage")

    def objects(self) -> list[dict]:
        """Every object entry (``objects``; the object-construction stage writes them)."""
        return self.require("objects", "the object-construction stage")

    def kept_objects(self) -> list[dict]:
        """The objects that are bodies of the scene (``is_kept``)."""
        return [o for o in self.objects() if is_kept(o)]

    def categories(self) -> dict[int, str | None]:
        """Instance id → category (None when the observation did not name one)."""
        return {inst["id"]: inst.get("category") for inst in self.data.get("instances") or []}

    def up(self) -> np.ndarray:
        """(3,) the scene's up, as decided once (``phirie_jax.frame``) and recorded in ``frame``.
        Folders written before the ``frame`` section keep it under ``construct.gravity``; +z
        when no stage decided one."""
        frame = self.data.get("frame") or (self.data.get("construct") or {}).get("gravity") or {}
        up = frame.get("up")
        return np.asarray(up if up is not None else (0.0, 0.0, 1.0), np.float64)

    def capture_to_world(self) -> np.ndarray | None:
        """(4, 4) the Sim(3) from the capture's frame to the scene's (``frame``), when recorded."""
        matrix = (self.data.get("frame") or {}).get("capture_to_world")
        return None if matrix is None else np.asarray(matrix, np.float64)

    def observed_surface(self) -> Path | None:
        """The surface the observation stage lifted onto (scan mesh or splat-derived), as a path
        to open; None when it recorded none."""
        path = ((self.data.get("observe") or {}).get("surface") or {}).get("path")
        return resolve(self.out_dir, path) if path else None

    def surface_paths(self) -> list[str]:
        """The scene surfaces earlier stages recorded, as written (the object stage's choice first,
        then the observation stage's)."""
        return [p for p in ((self.data.get("construct") or {}).get("surface"),
                            ((self.data.get("observe") or {}).get("surface") or {}).get("path")) if p]

    def support_records(self) -> dict[int, dict]:
        """Object id → the record of the support it stands on (``observe.support.Support.as_record``),
        as observation recorded it with the instance (older folders: as the object stage did)."""
        found = {int(s["id"]): {"normal": [0.0, 0.0, 1.0], "hits": 0, **s}
                 for s in (self.data.get("construct") or {}).get("supports") or [] if s.get("height") is not None}
        found.update({int(i["id"]): i["support"] for i in self.data.get("instances") or [] if i.get("support")})
        return found

    # --- which stages finished ---

    def stage_status(self) -> dict[str, str]:
        """Stage name → its status (``STAGE_NAMES``; "not run" for a stage never started). A folder
        written without ``stages`` (by an earlier version, or by a stage called on its own): a stage
        is complete when the section it writes last is there and it is not the ``failed_stage``."""
        recorded = self.data.get("stages")
        if isinstance(recorded, dict):
            return {name: str(recorded.get(name, "not run")) for name in STAGE_NAMES}
        failed = (self.data.get("failed_stage") or {}).get("stage")
        return {name: FAILED if name == failed else COMPLETE if self.data.get(section) is not None else "not run"
                for name, section in LAST_WRITTEN.items()}

    def mark_stage(self, name: str, status: str) -> None:
        if name not in STAGE_NAMES:
            raise ValueError(f"unknown stage {name!r}")
        stages = self.data.get("stages")
        self.data["stages"] = {**(stages if isinstance(stages, dict) else {}), name: status}

    def unfinished(self, stages: tuple[str, ...] = STAGE_NAMES) -> dict[str, str]:
        """The stages of ``stages`` that are not complete, with their status."""
        status = self.stage_status()
        return {name: status[name] for name in stages if status[name] != COMPLETE}

    def require_complete(self, stages: tuple[str, ...], needed_by: str) -> None:
        """``SceneInputError`` naming the first of ``stages`` that did not complete (``needed_by``
        says what needs them, e.g. "the drop tests")."""
        unfinished = self.unfinished(stages)
        if unfinished:
            name, status = next(iter(unfinished.items()))
            raise SceneInputError(self.path, "stages", f"the {name} stage {describe_status(status)} (expected a "
                                  f"complete conversion for {needed_by}: run phirie convert again)")

    def set(self, section: str, value: Any) -> None:
        """Replace one section (``schema`` and ``timings`` have their own methods)."""
        if section in ("schema", "timings"):
            raise ValueError(f"section {section!r} is managed by the manifest itself")
        self.data[section] = _plain(value)

    def upsert(self, section: str, items: list[dict], key: str = "id") -> None:
        """Add items to a list section, replacing those with the same ``key``; sorted by it."""
        current = {item[key]: item for item in self.data.get(section, [])}
        current.update({item[key]: _plain(item) for item in items})
        self.data[section] = [current[k] for k in sorted(current)]

    def record_timing(self, stage: str, seconds: float) -> None:
        self.data["timings"][stage] = round(float(seconds), 6)
        self._timed.add(stage)

    @contextlib.contextmanager
    def timed(self, name: str) -> Iterator[Elapsed]:
        """Time the block into ``timings[name]`` (also when it raises). The first block of a name
        in this run replaces an earlier run's value; later blocks of the same name add to it, so
        a step inside a loop records its total. Yields an ``Elapsed`` whose ``seconds`` is this
        block's time once it ends."""
        elapsed = Elapsed()
        start = time.perf_counter()
        try:
            yield elapsed
        finally:
            elapsed.seconds = time.perf_counter() - start
            before = self.data["timings"].get(name, 0.0) if name in self._timed else 0.0
            self.record_timing(name, before + elapsed.seconds)

    def write(self) -> Path:
        """Write ``manifest.json`` atomically (never half-written) and return its path."""
        ordered = {"schema": SCHEMA, **{k: v for k, v in self.data.items() if k != "schema"}}
        write_text(self.path, json.dumps(ordered, indent=2, allow_nan=False) + "\n")
        return self.path


def describe_status(status: str) -> str:
    """A stage's status as the end of a sentence ("the physics stage ...")."""
    return {RUNNING: "did not finish (the run was killed, or is still running)", FAILED: "failed",
            PENDING: "did not start (an earlier stage did not finish)", OUTDATED: "is outdated (an earlier "
            "stage ran again after it)", "not run": "has not run", "unknown": "did not finish (no record of "
            "the conversion's end)"}.get(status, f"is {status}")


def to_dict(config) -> dict:
    """A config as plain JSON-ready values (nested configs included)."""
    return dataclasses.asdict(config)
