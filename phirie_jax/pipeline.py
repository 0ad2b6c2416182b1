"""The whole conversion: scene folder → interactive scene folder.

Stages run in order, each reading and extending ``OUT/manifest.json``:
observe (instances) → objects (assets) → physics (collision, MJCF/URDF, drop tests) →
background (removal, inpainting targets, fill). The capture's cameras are written beside
the results (``transforms.json``) so the output folder is self-contained.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

from phirie_jax import layout
from phirie_jax.construct.background.config import BackgroundConfig
from phirie_jax.construct.objects.config import ObjectsConfig
from phirie_jax.construct.physics.config import PhysicsConfig
from phirie_jax.io.scene import load_scene
from phirie_jax.io.transforms_json import write_transforms_json
from phirie_jax.manifest import Manifest
from phirie_jax.observe.config import ObserveConfig
from phirie_jax.types import SceneInput


@dataclasses.dataclass(frozen=True)
class ConvertConfig:
    """Every stage's parameters (defaults: the paper's numbers).

    Attributes:
        observe: Scene Observation.
        objects: object candidates, registration, checks and selection.
        physics: collision, physics priors, export and drop tests (also the candidates'
            settling check while ranking).
        background: removal of the objects' source Gaussians, inpainting targets and the
            plane-disk fill of what they uncover.
    """

    observe: ObserveConfig = ObserveConfig()
    objects: ObjectsConfig = ObjectsConfig()
    physics: PhysicsConfig = PhysicsConfig()
    background: BackgroundConfig = BackgroundConfig()


@dataclasses.dataclass(frozen=True)
class Run:
    """What every stage of one conversion sees."""

    scene: SceneInput
    out_dir: Path
    config: ConvertConfig
    masks: str | Path | None = None


def _observe(run: Run) -> None:
    from phirie_jax.observe.stage import run_observe

    run_observe(run.scene.root, run.out_dir, run.config.observe, masks=run.masks, scene=run.scene)


def _objects(run: Run) -> None:
    from phirie_jax.construct.objects.stage import run_objects
    from phirie_jax.construct.physics.settling import candidate_settler

    run_objects(run.scene.root, run.out_dir, run.config.objects, scene=run.scene,
                settle=candidate_settler(run.config.physics))


def _physics(run: Run) -> None:
    from phirie_jax.construct.physics.stage import run_physics

    run_physics(run.scene.root, run.out_dir, run.config.physics)


def _background(run: Run) -> None:
    from phirie_jax.construct.background.stage import run_background

    run_background(run.scene.root, run.out_dir, run.config.background, scene=run.scene)


# The stage table: run in this order, each reading what the earlier ones wrote.
STAGES: dict[str, Callable[[Run], None]] = {
    "observe": _observe, "objects": _objects, "physics": _physics, "background": _background}


def _start(scene: SceneInput, out_dir: Path) -> None:
    """The output folder's manifest with the scene it converts, and the capture's cameras."""
    manifest = Manifest.load_or_create(out_dir)
    manifest.set("scene", {"path": str(scene.root), "layout": scene.layout,
                           "gaussians": str(scene.gaussians_path), "cameras": len(scene.cameras)})
    manifest.write()
    if scene.cameras:
        write_transforms_json(out_dir / layout.CAMERAS, list(scene.cameras))


def run_convert(scene_dir: str | Path, out_dir: str | Path, config: ConvertConfig = ConvertConfig(),
                masks: str | Path | None = None, gaussians: str | Path | None = None,
                surface: str | Path | None = None, progress=None) -> dict:
    """Run every stage of ``STAGES`` on ``scene_dir``; returns the final manifest (a dict).
    ``progress(stage)`` is called as each stage starts."""
    start = time.perf_counter()
    scene = load_scene(scene_dir, gaussians=gaussians, surface=surface)
    run = Run(scene, Path(out_dir), config, masks)
    _start(scene, run.out_dir)
    for name, stage in STAGES.items():
        if progress is not None:
            progress(name)
        stage(run)
    manifest = Manifest.load_or_create(run.out_dir)
    manifest.record_timing("convert", time.perf_counter() - start)
    manifest.write()
    return manifest.data
