"""Prompts' objects projected to every view as instance masks (step 4 of ``observe.prompt_lift``).

Every view is rendered with one feature channel per prompt (1 on its Gaussians): a pixel where
the prompt's Gaussians give at least half of the composited alpha shows it, so occlusion is the
renderer's own. An opaque Gaussian belongs to the first prompt that grew over it; a more
transparent one (haze, fur) to its nearest opaque Gaussian's prompt when close enough. Masks are
cleaned like box-prompt masks (``observe.box_prompt.clean_labels``) and given at the photos' size
like ``masks/`` files, labels = prompt numbers, categories = the prompts' labels.
``PromptMasks`` is the observation stage's mask source; the splat-derived surface renders the
same Gaussians at the same cameras and hands it each render, so every view is rendered once.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np

from phirie_jax.observe.box_prompt import clean_labels
from phirie_jax.observe.masks import Segment, ViewFailure, ViewMasks, camera_problem
from phirie_jax.observe.prompt_config import PromptConfig
from phirie_jax.observe.prompt_lift import LiftedPrompt, Solid, lift_prompt, rendered_set, working
from phirie_jax.observe.prompts import Prompt
from phirie_jax.observe.support import Support, Wall, is_wall
from phirie_jax.types import Camera, GaussianSplatData


def owners(gaussians: GaussianSplatData, solid: Solid, tree, lifted: Sequence[LiftedPrompt],
           config: PromptConfig) -> np.ndarray:
    """(N,) int: the prompt id each rendered Gaussian belongs to (0 = none). An opaque Gaussian
    belongs to the first prompt whose members hold it; a more transparent one to its nearest
    opaque Gaussian's prompt, when within ``attach_factor`` × that prompt's link radius."""
    solid_owner = np.zeros(len(solid.points), np.int64)
    links = {}
    for item in lifted:
        if item.members is not None:
            free = item.members[solid_owner[item.members] == 0]
            solid_owner[free] = item.id
            links[item.id] = item.link
    out = np.zeros(gaussians.num, np.int64)
    if not links:
        return out
    distance, nearest = tree.query(gaussians.means.astype(np.float64))
    owner = solid_owner[nearest]
    link_of = np.zeros(max(links) + 1)
    link_of[list(links)] = list(links.values())
    near = (owner > 0) & (distance <= config.attach_factor * link_of[owner])
    out[near] = owner[near]
    out[solid.rows] = solid_owner
    return out


def owner_labels(features: np.ndarray, alpha: np.ndarray, ids: Sequence[int], config: PromptConfig) -> np.ndarray:
    """(H, W) uint16 labels of one view from its rendered per-prompt features (H, W, P) and alpha
    (H, W): prompt k where its Gaussians give at least half the pixel's alpha, cleaned."""
    share = features / np.maximum(alpha, 1e-6)[..., None]
    best = np.argmax(share, axis=-1)
    shown = (np.take_along_axis(share, best[..., None], -1)[..., 0] >= 0.5) & (alpha >= config.min_alpha)
    labels = np.where(shown, np.asarray(ids, np.uint16)[best], 0).astype(np.uint16)
    return clean_labels(labels, ids, config.open_px, config.close_px, config.min_component)


def prompt_masks(gaussians: GaussianSplatData, cameras: Sequence[Camera], owner: np.ndarray,
                 lifted: Sequence[LiftedPrompt], config: PromptConfig, working_width: int,
                 rendered: dict[int, np.ndarray] | None = None) -> Iterator[ViewMasks | ViewFailure]:
    """Per-view masks of the lifted prompts (ids = prompt numbers, categories = labels), at the
    photos' size; a view that cannot be rendered is a ``ViewFailure``. ``rendered``: labels (at
    the working size) of views already rendered (``PromptMasks.take``)."""
    import cv2

    from phirie_jax.render import prepared, render

    done = [item for item in lifted if item.members is not None]
    if not done:
        return
    ids = [item.id for item in done]
    features = owner_features(owner, ids)
    kernel = prepared(gaussians.to_host_kernel())
    categories = {item.id: item.prompt.label for item in done}
    for view, original in enumerate(cameras):
        labels = (rendered or {}).get(view)
        if labels is None:
            problem = camera_problem(original)
            if problem is None:
                try:
                    out = render(kernel, working(original, working_width), features=features)
                except RuntimeError as err:   # the scene does not fit the renderer's buffers
                    problem = f"render failed: {err}"
            if problem:
                yield ViewFailure(view, original.name, problem)
                continue
            labels = owner_labels(np.asarray(out.features, np.float64), np.asarray(out.alpha, np.float64), ids, config)
        if labels.shape != (original.height, original.width):
            labels = cv2.resize(labels, (original.width, original.height), interpolation=cv2.INTER_NEAREST)
        present = [int(k) for k in np.unique(labels) if k]
        yield ViewMasks(view, labels.astype(np.int64), {k: Segment(k, k, categories.get(k)) for k in present},
                        "prompts")


def owner_features(owner: np.ndarray, ids: Sequence[int]) -> np.ndarray:
    """(N, P) float32: 1 where Gaussian n belongs to prompt ``ids[p]``."""
    return (owner[:, None] == np.asarray(ids)[None]).astype(np.float32)


def lift_prompts(gaussians: GaussianSplatData, cameras: Sequence[Camera], prompts: Sequence[Prompt],
                 config, working_width: int) -> tuple[GaussianSplatData, np.ndarray, np.ndarray, list[LiftedPrompt]]:
    """(the rendered set, its rows in ``gaussians``, each rendered Gaussian's owner, the lifted
    prompts) for ``ObserveConfig`` ``config`` (its ``surface.floaters`` and ``prompts``)."""
    rendered, rows = rendered_set(gaussians, config.surface.floaters)
    solid = Solid.of(rendered, config.prompts.min_opacity)
    tree = solid.tree()
    lifted = [lift_prompt(k, p, cameras, rendered, solid, tree, config.prompts, working_width)
              for k, p in enumerate(prompts, start=1)]
    return rendered, rows, owners(rendered, solid, tree, lifted, config.prompts), lifted


def prompt_supports(lifted: Sequence[LiftedPrompt]) -> dict[int, Support]:
    """Prompt id → the support its lift found under the object (``prompt_lift.find_support``: the
    peak of the flat, up-facing Gaussians below it, with the cameras above it), for the lifted
    prompts that found one. It is where the object meets what it stands on; rays around the
    footprint (``observe.support``) land on whatever lies around it, which on a soft support (a
    duvet the object sinks into) is centimetres lower, and a hull carved down to there grows a
    rounded underside that the object rocks on."""
    found = {}
    for item in lifted:
        record = item.record.get("support") if item.members is not None else None
        if record and "height" in record:
            found[item.id] = Support(float(record["height"]), "prompt", int(record["gaussians"]),
                                     np.array([0.0, 0.0, 1.0]))
    return found


def prompt_walls(lifted: Sequence[LiftedPrompt]) -> dict[int, Wall]:
    """Prompt id → the nearest near-vertical background plane its object stands in front of
    (``prompt_lift.background_planes`` used as background, ``support.is_wall``), for the lifted
    prompts that found one: what holds the object if it is mounted (``ObjectsConfig.mount_gap``)."""
    found = {}
    for item in lifted:
        if item.members is None:
            continue
        walls = [p for p in item.record.get("background_planes", ())
                 if p.get("used") and "object_gap" in p and is_wall(p["normal"])]
        if walls:
            plane = min(walls, key=lambda p: p["object_gap"])
            found[item.id] = Wall(np.asarray(plane["normal"], np.float64), float(plane["offset"]),
                                  float(plane["object_gap"]), f"a background plane behind prompt {item.id}'s object")
    return found


PROMPT_RECORD = "observe/prompts.npz"   # each prompt's Gaussians: rows of the scene's PLY and their owner


class PromptMasks:
    """The observation stage's mask source for prompts (``PromptMasks.lift``, then ``views``).
    The splat-derived surface renders the same Gaussians at the same cameras: with ``features``
    riding along, ``take`` keeps each view's labels, so every view is rendered once."""

    def __init__(self, rendered: GaussianSplatData, owner: np.ndarray, lifted: list[LiftedPrompt], cameras,
                 config):
        self.rendered, self.owner, self.lifted, self.cameras, self.config = rendered, owner, lifted, cameras, config
        self.ids = [item.id for item in lifted if item.members is not None]
        self.features = owner_features(owner, self.ids) if self.ids else None
        self.labels: dict[int, np.ndarray] = {}

    @staticmethod
    def lift(scene, prompts: Sequence[Prompt], config, record: dict, out_dir) -> PromptMasks:
        """Lift the prompts (``record["prompts"]``: one entry per prompt, what was decided, or why it
        could not be lifted) and write which of the scene's Gaussians each took (``PROMPT_RECORD``:
        ``rows`` into the scene's Gaussian PLY and ``owner``, the prompt id)."""
        import io
        import time
        from pathlib import Path

        from phirie_jax.io.atomic import write_bytes

        start = time.perf_counter()
        rendered, rows, owner, lifted = lift_prompts(scene.require_gaussians(), scene.cameras, prompts, config,
                                                     config.working_width)
        taken = owner > 0
        buffer = io.BytesIO()
        np.savez_compressed(buffer, rows=rows[taken].astype(np.int64), owner=owner[taken].astype(np.int32))
        write_bytes(Path(out_dir) / PROMPT_RECORD, buffer.getvalue())
        record["prompts"] = {"lifted": [item.record for item in lifted], "gaussians": PROMPT_RECORD,
                             "lift_s": round(time.perf_counter() - start, 3)}
        return PromptMasks(rendered, owner, lifted, scene.cameras, config)

    def renders(self, gaussians: GaussianSplatData) -> bool:
        """Whether ``gaussians`` are the set the prompts' features belong to (the same floater rule)."""
        return self.features is not None and gaussians.num == self.rendered.num and bool(
            np.array_equal(gaussians.means, self.rendered.means))

    def take(self, view: int, output) -> None:
        """Keep the labels of a render (with ``features``) of camera ``view`` at the working width."""
        self.labels[view] = owner_labels(np.asarray(output.features, np.float64), np.asarray(output.alpha, np.float64),
                                         self.ids, self.config.prompts)

    def supports(self) -> dict[int, Support]:
        """Prompt id → the support its lift found (``prompt_supports``)."""
        return prompt_supports(self.lifted)

    def walls(self) -> dict[int, Wall]:
        """Prompt id → the wall behind its object (``prompt_walls``)."""
        return prompt_walls(self.lifted)

    def views(self) -> Iterator[ViewMasks | ViewFailure]:
        return prompt_masks(self.rendered, self.cameras, self.owner, self.lifted, self.config.prompts,
                            self.config.working_width, self.labels)
