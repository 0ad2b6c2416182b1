"""The whole conversion: scene folder → interactive scene folder.

Stages run in order, each reading and extending ``OUT/manifest.json``:
observe (instances) → objects (assets) → physics (collision, MJCF/URDF, drop tests) →
background (removal, inpainting targets, fill). The capture's cameras are written beside
the results (``transforms.json``) so the output folder is self-contained.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

from phirie_jax.construct.background.config import BackgroundConfig
from phirie_jax.construct.objects.config import ObjectsConfig
from phirie_jax.construct.physics.config import PhysicsConfig
from phirie_jax.io.scene import load_scene
from phirie_jax.io.transforms_json import write_transforms_json
from phirie_jax.manifest import Manifest
from phirie_jax.observe.config import ObserveConfig

STAGES = ("observe", "objects", "physics", "background")


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


def run_convert(scene_dir: str | Path, out_dir: str | Path, config: ConvertConfig = ConvertConfig(),
                masks: str | Path | None = None, gaussians: str | Path | None = None,
                surface: str | Path | None = None, strict: bool = False, progress=None) -> dict:
    """Run every stage on ``scene_dir``; returns the final manifest (a dict).

    ``strict`` rejects an object whose best candidate fails a check instead of keeping it;
    ``progress(stage)`` is called as each stage starts.
    """
    from phirie_jax.construct.background.stage import run_background
    from phirie_jax.construct.objects.stage import run_objects
    from phirie_jax.construct.physics.settling import candidate_settler
    from phirie_jax.construct.physics.stage import run_physics
    from phirie_jax.observe.stage import run_observe

    out_dir = Path(out_dir)
    scene = load_scene(scene_dir, gaussians=gaussians, surface=surface)
    start = time.perf_counter()
    manifest = Manifest.load_or_create(out_dir)
    manifest.set("scene", {"path": str(scene.root), "layout": scene.layout,
                           "gaussians": str(scene.gaussians_path), "cameras": len(scene.cameras)})
    manifest.write()
    if scene.cameras:
        write_transforms_json(out_dir / "transforms.json", list(scene.cameras))

    def stage(name):
        if progress is not None:
            progress(name)

    stage("observe")
    run_observe(scene_dir, out_dir, config.observe, masks=masks, scene=scene)
    stage("objects")
    run_objects(scene_dir, out_dir, config.objects, strict=strict, scene=scene,
                settle=candidate_settler(config.physics))
    stage("physics")
    run_physics(scene_dir, out_dir, config.physics)
    stage("background")
    run_background(scene_dir, out_dir, config.background, scene=scene)
    manifest = Manifest.load_or_create(out_dir)
    manifest.record_timing("convert", time.perf_counter() - start)
    manifest.write()
    return manifest.data
