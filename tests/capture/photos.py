"""Photos with known cameras for the capture tests: ``phirie synth``'s renderer on an arc of views.

The synthetic tabletop (``phirie_jax.synthetic.build_scene``) is rendered from ``count`` cameras
on a ring arc around it, looking at the table's centre, as a hand-held orbit would be taken.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from phirie_jax.io.camera import intrinsics_matrix
from phirie_jax.types import Camera

ARC_DEG = 110.0        # the arc the cameras span (10° between neighbours for 12)
RING = (1.2, 1.3)      # m: radius and height of the ring
TARGET = (0.0, 0.0, 0.8)
FOV_DEG = 55.0


def arc_cameras(count: int, width: int, height: int) -> list[Camera]:
    from phirie_jax.synthetic.scene import look_at

    focal = 0.5 * width / np.tan(np.deg2rad(FOV_DEG) / 2)
    K = intrinsics_matrix(focal, focal, width / 2, height / 2)
    cameras = []
    for i, angle in enumerate(np.deg2rad(np.linspace(-ARC_DEG / 2, ARC_DEG / 2, count))):
        eye = np.array([RING[0] * np.cos(angle), RING[0] * np.sin(angle), RING[1]])
        cameras.append(Camera(f"{i:04d}.png", K, look_at(eye, np.asarray(TARGET)), width, height))
    return cameras


def render_photos(folder: Path, count: int = 12, width: int = 320, preset: str = "tiny", seed: int = 0
                  ) -> list[Camera]:
    """``count`` PNG photos of the preset's scene in ``folder``; returns their true cameras."""
    from phirie_jax.synthetic.scene import build_scene, render_views, write_png

    cameras = arc_cameras(count, width, width * 3 // 4)
    scene = dataclasses.replace(build_scene(preset, seed), cameras=cameras)
    images, _ = render_views(scene)
    for cam, image in zip(cameras, images):
        write_png(Path(folder) / cam.name, image)
    return cameras
