"""Small exact scenes for the observation tests: meshes, cameras and masks projected from
meshes (no splat rendering), and a scene folder written like a real capture."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from phirie_jax.io.camera import intrinsics_matrix
from phirie_jax.synthetic.scene import look_at
from phirie_jax.types import Camera


def ring(n: int, radius: float, height: float, target=(0.0, 0.0, 0.0), width=80, height_px=60, focal=70.0,
         offset: float = 0.0) -> list[Camera]:
    K = intrinsics_matrix(focal, focal, width / 2, height_px / 2)
    cams = []
    for i in range(n):
        a = offset + 2 * np.pi * i / n
        eye = np.array([radius * np.cos(a), radius * np.sin(a), height])
        cams.append(Camera(f"{i:04d}.png", K, look_at(eye, np.asarray(target, float)), width, height_px))
    return cams


def id_masks(meshes: dict[int, object], background, cameras: list[Camera]) -> list[np.ndarray]:
    """Per-view 16-bit masks of the first hit: object id, 0 for the background mesh."""
    import trimesh

    from phirie_jax.observe.masks import vertex_label_image
    from phirie_jax.observe.raycast import Raycaster

    parts = [background, *meshes.values()]
    labels = np.concatenate([np.zeros(len(background.vertices), np.int64),
                             *[np.full(len(m.vertices), k, np.int64) for k, m in meshes.items()]])
    scene = trimesh.util.concatenate(parts)
    caster = Raycaster(scene.vertices, scene.faces)
    return [vertex_label_image(caster, labels, cam).astype(np.uint16) for cam in cameras]


def write_png(path: Path, image: np.ndarray) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), image)


def tabletop_folder(root: Path, num_cameras: int = 10, width: int = 240, height: int = 180, seed: int = 0):
    """A scene folder from ``build_scene('tiny', seed)`` geometry: transforms.json, grey images,
    surface.ply, masks projected from the ground-truth meshes, gt/objects.json."""
    import trimesh

    from phirie_jax.io.transforms_json import write_transforms_json
    from phirie_jax.synthetic import build_scene
    from phirie_jax.synthetic.scene import surface_mesh, write_ground_truth

    scene = build_scene("tiny", seed)
    cams = ring(num_cameras, 0.9, 1.45, target=(0.0, 0.0, 0.78), width=width, height_px=height, focal=0.9 * width)
    furniture = trimesh.util.concatenate([scene.furniture.floor, scene.furniture.table])
    masks = id_masks({o.id: o.world_mesh() for o in scene.objects}, furniture, cams)
    for cam, mask in zip(cams, masks):
        write_png(root / "images" / cam.name, np.full((height, width, 3), 128, np.uint8))
        write_png(root / "masks" / cam.name, mask)
    write_transforms_json(root / "transforms.json", cams)
    surface_mesh(scene).export(root / "surface.ply")
    write_ground_truth(scene, root)
    return scene, cams, masks


def ground_truth_ids(root: Path) -> list[int]:
    return [o["id"] for o in json.loads((root / "gt" / "objects.json").read_text())]
