"""A scene folder copied into another frame: the same capture as a non-metric, tilted one.

``reframe_scene(source, destination, world_to_capture)`` moves the Gaussians, the cameras and
the surface mesh by a Sim(3) and copies images and masks as they are; ground truth (``gt/``)
is copied unchanged, so it stays in the source's frame. The copy declares no frame
(``frame.json`` is left out): converting it exercises the frame estimate, or the options.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from phirie_jax.frame.resolve import scene_in_world
from phirie_jax.io.mesh import load_trimesh
from phirie_jax.io.ply import write_gaussian_ply
from phirie_jax.io.scene import load_scene
from phirie_jax.io.transforms_json import write_transforms_json
from phirie_jax.synthetic.scene import write_mesh

COPIED = ("images", "masks", "gt", "candidates")


def reframe_scene(source: str | Path, destination: str | Path, world_to_capture: np.ndarray) -> Path:
    """Write ``destination``: ``source`` (a scene folder) moved by ``world_to_capture`` (4, 4) Sim(3),
    with nerfstudio cameras (``transforms.json``) whatever the source's layout."""
    source, destination = Path(source), Path(destination)
    scene = load_scene(source)
    moved = scene_in_world(scene, np.asarray(world_to_capture, np.float64))
    destination.mkdir(parents=True, exist_ok=True)
    for name in COPIED:
        if (source / name).is_dir():
            shutil.copytree(source / name, destination / name, dirs_exist_ok=True)
    write_gaussian_ply(destination / "point_cloud.ply", moved.require_gaussians())
    write_transforms_json(destination / "transforms.json", list(moved.cameras))
    if scene.surface_mesh is not None:
        mesh = load_trimesh(scene.surface_mesh)
        mesh.vertices = moved.to_world(mesh.vertices)
        write_mesh(destination / scene.surface_mesh.name, mesh)
    return destination
