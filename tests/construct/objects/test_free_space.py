"""The visual hull's free-space carving: a silhouette cannot carve a cup's well, what the views saw
through to its floor can; a ray that meets no observed surface carves nothing."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
import trimesh

from phirie_jax.construct.objects.config import ObjectsConfig
from phirie_jax.construct.objects.generators import InstanceInput, visual_hull
from phirie_jax.frame.gravity import gravity_frame
from phirie_jax.io.camera import intrinsics_matrix
from phirie_jax.observe.raycast import Raycaster
from phirie_jax.observe.support import Support
from phirie_jax.synthetic.scene import look_at
from phirie_jax.types import Camera

W = H = 96
SIDE, WALL = 0.12, 0.015   # the cup: 12 cm square, 12 cm tall, walls and floor 1.5 cm thick
CONFIG = dataclasses.replace(ObjectsConfig(), hull_resolution=48)


def cup() -> trimesh.Trimesh:
    """An open-top square cup standing on z = 0 (overlapping slabs: ray casting needs no union)."""
    h, s, w = SIDE, SIDE, WALL
    slabs = [((s, s, w), (0, 0, w / 2)),
             ((w, s, h), ((s - w) / 2, 0, h / 2)), ((w, s, h), (-(s - w) / 2, 0, h / 2)),
             ((s, w, h), (0, (s - w) / 2, h / 2)), ((s, w, h), (0, -(s - w) / 2, h / 2))]
    return trimesh.util.concatenate([trimesh.creation.box(extents=e, transform=trimesh.transformations.translation_matrix(c))
                                     for e, c in slabs])


def cameras() -> list[Camera]:
    K = intrinsics_matrix(110.0, 110.0, W / 2, H / 2)
    eyes = [np.array([r * np.cos(a), r * np.sin(a), z]) for r, z in ((0.45, 0.25), (0.3, 0.45), (0.1, 0.5))
            for a in np.linspace(0, 2 * np.pi, 6, endpoint=False)]
    return [Camera(f"v{k}.png", K, look_at(e, np.array([0.0, 0.0, 0.05])), W, H) for k, e in enumerate(eyes)]


def instance(tmp_path, surface) -> InstanceInput:
    """The cup's instance: its masks rendered by ray casting, Q its surface seen from the views."""
    mesh = Raycaster(cup().vertices, cup().faces)
    cams, paths, seen = cameras(), [], []
    for k, cam in enumerate(cams):
        hits, _, _ = mesh.cast_camera(cam)
        labels = hits.hit.reshape(H, W).astype(np.uint16)
        path = tmp_path / cam.name
        cv2.imwrite(str(path), labels)
        paths.append(path)
        seen.append(hits.points[hits.hit])
    points = np.concatenate(seen)
    frame = gravity_frame(np.array([0.0, 0.0, 1.0]), "test")
    support = Support(0.0, "surface", 100, np.array([0.0, 0.0, 1.0]))
    return InstanceInput(1, points[points[:, 2] > 0.006], frame, support, tuple(cams), tuple(paths),
                         (1,) * len(cams), surface)


def well_fraction(shape) -> float:
    """Fraction of the well's inside (the cup's hollow, away from its walls) the shape fills."""
    mesh = trimesh.Trimesh(shape.vertices + shape.placement[:3, 3], shape.faces)
    grid = np.stack(np.meshgrid(*[np.linspace(-0.02, 0.02, 5)] * 2, np.linspace(0.05, 0.10, 4), indexing="ij"),
                    -1).reshape(-1, 3)
    return float(np.mean(Raycaster(mesh.vertices, mesh.faces).within(grid, 0.0)))


def test_the_views_see_into_the_well_that_the_silhouettes_fill(tmp_path):
    silhouettes = visual_hull(instance(tmp_path, None), CONFIG)
    carved = visual_hull(instance(tmp_path, Raycaster(cup().vertices, cup().faces)), CONFIG)
    assert silhouettes.info["seen_through"] == 0 and well_fraction(silhouettes) > 0.9
    assert carved.info["seen_through"] > 0 and well_fraction(carved) < 0.2
    # the walls stay: the carved cup still stands as tall and as wide as the cup
    extent = carved.vertices.max(0) - carved.vertices.min(0)
    assert extent == pytest.approx([SIDE, SIDE, SIDE], abs=0.02)


def test_a_ray_that_meets_no_observed_surface_is_no_evidence_of_free_space(tmp_path):
    elsewhere = trimesh.creation.box(extents=(0.01, 0.01, 0.01),
                                     transform=trimesh.transformations.translation_matrix((5.0, 5.0, -5.0)))
    carved = visual_hull(instance(tmp_path, Raycaster(elsewhere.vertices, elsewhere.faces)), CONFIG)
    assert carved.info["seen_through"] == 0 and well_fraction(carved) > 0.9


def test_the_views_needed_and_the_margin_are_the_configs(tmp_path):
    surface = Raycaster(cup().vertices, cup().faces)
    off = visual_hull(instance(tmp_path, surface), dataclasses.replace(CONFIG, hull_free_space_views=0))
    too_many = visual_hull(instance(tmp_path, surface), dataclasses.replace(CONFIG, hull_free_space_views=19))
    deep = visual_hull(instance(tmp_path, surface), dataclasses.replace(CONFIG, hull_free_space_margin=0.2))
    assert off.info["seen_through"] == too_many.info["seen_through"] == deep.info["seen_through"] == 0
