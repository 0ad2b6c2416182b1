"""The synthetic tabletop: deterministic, physically sensible, written like a real capture."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from phirie_jax.synthetic import PRESETS, build_scene
from phirie_jax.synthetic.scene import _inside_footprint
from phirie_jax.synthetic.shapes import CATEGORIES, make_object

ON_SURFACE_TOL = 0.002  # surface Gaussians sit on their mesh (sampling is exact; float32 storage)


@pytest.fixture(scope="module")
def tiny():
    return build_scene("tiny", seed=3)


def test_same_seed_same_scene_other_seed_other_scene(tiny):
    again = build_scene("tiny", seed=3)
    np.testing.assert_array_equal(again.capture.data.means, tiny.capture.data.means)
    np.testing.assert_array_equal(again.capture.data.sh, tiny.capture.data.sh)
    other = build_scene("tiny", seed=4)
    assert other.capture.data.num != tiny.capture.data.num or not np.array_equal(
        other.capture.data.means, tiny.capture.data.means)


@pytest.mark.parametrize("category", CATEGORIES)
def test_object_meshes_are_watertight_canonical_and_metric(category):
    shape = make_object(category, np.random.default_rng(0), 0)
    mesh = shape.mesh
    assert mesh.is_watertight and mesh.volume > 0
    lo, hi = mesh.bounds
    assert abs(lo[2]) < 1e-9, "rests on z = 0"
    assert 0.03 < hi[2] < 0.3 and np.all(hi[:2] - lo[:2] < 0.25), "household size in metres"
    rgb = shape.colour(mesh.vertices)
    assert rgb.shape == (len(mesh.vertices), 3) and rgb.min() >= 0 and rgb.max() <= 1


def test_placements_are_on_the_table_and_do_not_overlap(tiny):
    lo, hi = PRESETS["tiny"].num_objects
    assert lo <= len(tiny.objects) <= hi
    half = tiny.furniture.top_extent / 2
    footprints = []
    for obj in tiny.objects:
        world = obj.world_mesh()
        assert abs(world.bounds[0, 2] - tiny.furniture.table_top_z) < 1e-9
        assert np.all(np.abs(world.vertices[:, :2]) < half)
        rot = obj.pose[:3, :3]
        np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-12)
        footprints.append(world)
    for i in range(len(footprints)):
        for j in range(i + 1, len(footprints)):
            a, b = footprints[i].bounds, footprints[j].bounds
            radius_i = np.linalg.norm(tiny.objects[i].shape.mesh.vertices[:, :2], axis=1).max()
            radius_j = np.linalg.norm(tiny.objects[j].shape.mesh.vertices[:, :2], axis=1).max()
            gap = np.linalg.norm(tiny.objects[i].pose[:2, 3] - tiny.objects[j].pose[:2, 3])
            assert gap > radius_i + radius_j, (a, b)


def test_tabletop_under_objects_is_missing_from_capture_but_in_ground_truth(tiny):
    top = tiny.furniture.table_top_z
    for name, gaussians, expect_hidden in (("capture", tiny.capture, False), ("gt", tiny.background, True)):
        bg = gaussians.labels == 0
        on_top = bg & (np.abs(gaussians.data.means[:, 2] - top) < 1e-4)
        under = np.zeros(len(on_top), bool)
        for obj in tiny.objects:
            under[on_top] |= _inside_footprint(gaussians.data.means[on_top, :2], obj)
        assert (under.sum() > 0) == expect_hidden, name


def test_surface_gaussians_lie_on_their_object_and_labels_match(tiny):
    data, labels = tiny.capture.data, tiny.capture.labels
    assert set(np.unique(labels)) == {0, *[o.id for o in tiny.objects]}
    opaque = data.opacity_logits > 1.0  # surface disks, not blur or floaters
    for obj in tiny.objects:
        pts = data.means[(labels == obj.id) & opaque]
        _, dist, _ = trimesh.proximity.closest_point(obj.world_mesh(), pts[:300])
        assert np.max(dist) < ON_SURFACE_TOL


def test_capture_has_sh3_view_dependence_and_realistic_defects(tiny):
    data, labels = tiny.capture.data, tiny.capture.labels
    assert data.sh_degree == 3
    band_energy = np.linalg.norm(data.sh[:, 1:], axis=(1, 2))
    assert 0 < np.median(band_energy) < 0.5 * np.median(np.linalg.norm(data.sh[:, 0], axis=1))
    opacity = 1 / (1 + np.exp(-data.opacity_logits))
    floaters = (labels == 0) & (data.means[:, 2] > tiny.furniture.table_top_z + 0.05)
    assert floaters.sum() == PRESETS["tiny"].floaters and np.all(opacity[floaters] < 0.6)
    blur = (labels > 0) & (opacity < 0.4)
    assert blur.sum() == PRESETS["tiny"].boundary_blobs * len(tiny.objects)
    scales = np.exp(data.log_scales[labels > 0])
    flat = scales.min(1) / scales.max(1)
    assert np.median(flat) < 0.2, "surface Gaussians are flat disks"


def test_cameras_see_the_table(tiny):
    assert len(tiny.cameras) == PRESETS["tiny"].num_cameras
    centre = np.array([[0, 0, tiny.furniture.table_top_z]])
    for cam in tiny.cameras:
        uv, depth = cam.project(centre)
        assert depth[0] > 0.5
        assert 0 <= uv[0, 0] < cam.width and 0 <= uv[0, 1] < cam.height
    assert json.dumps([c.name for c in tiny.cameras])


def test_crowded_preset_places_thirty_objects_apart_on_its_table():
    from phirie_jax.synthetic import shapes
    from phirie_jax.synthetic.scene import PLACEMENT_GAP, place_objects

    config = PRESETS["crowded"]
    furniture = shapes.make_furniture(floor_size=config.floor_size, top=config.table_top)
    objects = place_objects(np.random.default_rng(5), config, furniture, 5)
    assert len(objects) == 30 and len({o.id for o in objects}) == 30
    centres = np.array([o.pose[:2, 3] for o in objects])
    radii = np.array([np.linalg.norm(o.shape.mesh.vertices[:, :2], axis=1).max() for o in objects])
    gaps = np.linalg.norm(centres[:, None] - centres[None], axis=-1) - radii[:, None] - radii[None]
    assert gaps[~np.eye(30, dtype=bool)].min() > PLACEMENT_GAP - 1e-9
    assert np.all(np.abs(centres) + radii[:, None] <= furniture.top_extent / 2)
