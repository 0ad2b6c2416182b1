"""First-hit lifting on exact geometry, mask erosion against a brute-force loop, and
bad mask input (wrong size, a listed id with no pixels, a view without a pose)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import trimesh

from phirie_jax.errors import SceneInputError
from phirie_jax.observe.config import ObserveConfig
from phirie_jax.observe.lift import interior, lift_view
from phirie_jax.observe.masks import Segment, ViewFailure, ViewMasks, external_masks, file_masks, read_label_png
from phirie_jax.observe.raycast import Raycaster
from tests.observe.helpers import ring, write_png

EXACT_TOL = 1e-5  # float32 ray casting of metre-scale geometry
CONFIG = ObserveConfig(pixel_stride=1, mask_erosion_px=0, min_proposal_points=1)


def plane_caster(z=0.0, half=5.0):
    verts = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]])
    return Raycaster(verts, np.array([[0, 1, 2], [0, 2, 3]]))


def test_lifting_onto_a_plane_is_the_ray_plane_intersection():
    cam = ring(1, 1.0, 0.8, width=40, height_px=30, focal=35.0, offset=0.3)[0]
    labels = np.zeros((30, 40), np.int64)
    labels[5:20, 8:30] = 7
    masks = ViewMasks(0, labels, {7: Segment(7, 7)}, "mem")
    proposals, rejected = lift_view(plane_caster(), cam, masks, CONFIG)
    assert not rejected and len(proposals) == 1
    p = proposals[0]
    assert p.pixels == 15 * 22 and len(p.points) == 15 * 22 and p.bbox == (8, 5, 29, 19)
    # analytic: pixel centre (i + 0.5, j + 0.5) back-projected to z = 0
    jj, ii = np.mgrid[5:20, 8:30]
    rays = np.stack([ii + 0.5, jj + 0.5, np.ones_like(ii, float)], -1).reshape(-1, 3) @ np.linalg.inv(cam.K).T
    rays = rays @ cam.camera_to_world[:3, :3].T
    t = -cam.center[2] / rays[:, 2]
    np.testing.assert_allclose(p.points, cam.center + t[:, None] * rays, atol=EXACT_TOL)


def test_lifting_onto_a_box_lands_on_its_visible_faces():
    box = trimesh.creation.box(extents=[0.3, 0.2, 0.25])
    cam = ring(1, 0.9, 0.6, width=64, height_px=48, focal=60.0, offset=0.7)[0]
    caster = Raycaster(box.vertices, box.faces)
    depth = caster.depth_map(cam)
    labels = np.where(depth > 0, 3, 0)
    (p,), _ = lift_view(caster, cam, ViewMasks(0, labels, {3: Segment(3, 3)}), CONFIG)
    assert len(p.points) == (depth > 0).sum() > 200
    # on the surface: one coordinate at ±half extent, the others inside
    half = np.array([0.15, 0.1, 0.125])
    on_face = np.isclose(np.abs(p.points), half, atol=EXACT_TOL)
    assert np.all(on_face.sum(1) >= 1) and np.all(np.abs(p.points) <= half + EXACT_TOL)
    # only faces that look at the camera: outward normal · (camera − point) > 0
    normal = np.where(on_face, np.sign(p.points), 0.0)
    assert np.all(np.sum(normal * (cam.center - p.points), axis=1) > 0)


def test_rays_that_miss_are_not_lifted():
    cam = ring(1, 1.0, 0.0, width=20, height_px=10, focal=20.0)[0]  # horizontal: half the rays miss z = −0.05
    labels = np.ones((10, 20), np.int64)
    (p,), _ = lift_view(plane_caster(z=-0.05), cam, ViewMasks(0, labels, {1: Segment(1, 1)}), CONFIG)
    assert 0 < len(p.points) < 200 and np.all(np.isfinite(p.points))


def test_interior_matches_brute_force():
    rng = np.random.default_rng(1)
    labels = rng.integers(0, 3, size=(9, 11))
    labels[2:7, 3:9] = 5
    for radius in (0, 1, 2):
        fast = interior(labels, radius)
        slow = np.zeros_like(fast)
        for y in range(9):
            for x in range(11):
                win = labels[max(0, y - radius): y + radius + 1, max(0, x - radius): x + radius + 1]
                slow[y, x] = labels[y, x] > 0 and np.all(win == labels[y, x])
        np.testing.assert_array_equal(fast, slow)


def test_proposal_too_small_is_recorded():
    cam = ring(1, 1.0, 0.8, width=40, height_px=30, focal=35.0)[0]
    labels = np.zeros((30, 40), np.int64)
    labels[10, 10] = 4
    config = dataclasses.replace(CONFIG, min_proposal_points=3)
    proposals, rejected = lift_view(plane_caster(), cam, ViewMasks(0, labels, {4: Segment(4, 4)}), config)
    assert proposals == [] and "1 lifted points (< 3)" in rejected[0]["reason"]


def test_mask_of_the_wrong_size_is_a_clear_error_and_a_recorded_skip(tmp_path):
    cams = ring(2, 1.0, 0.8, width=40, height_px=30)
    write_png(tmp_path / "0000.png", np.zeros((30, 40), np.uint16))
    write_png(tmp_path / "0001.png", np.zeros((31, 40), np.uint16))
    with pytest.raises(SceneInputError, match=r"0001.png: mask size: 40×31 \(expected 40×30"):
        read_label_png(tmp_path / "0001.png", cams[1])
    items = list(file_masks(tuple(cams), (tmp_path / "0000.png", tmp_path / "0001.png")))
    assert isinstance(items[0], ViewMasks)
    assert isinstance(items[1], ViewFailure) and items[1].view == 1 and "mask size" in items[1].reason


def test_external_masks_listed_id_without_pixels_and_view_without_pose(tmp_path):
    cams = ring(3, 1.0, 0.8, width=40, height_px=30)
    cams[2] = dataclasses.replace(cams[2], world_to_camera=np.full((4, 4), np.nan))
    mask = np.zeros((30, 40), np.uint16)
    mask[5:15, 5:15] = 1
    for i in range(3):
        write_png(tmp_path / f"{i:04d}.png", mask)
    write_png(tmp_path / "9999.png", mask)  # no camera of that name
    (tmp_path / "0000.json").write_text(json.dumps({"segments": [{"label": 1, "score": 0.9, "category": "mug"},
                                                                 {"label": 3, "score": 0.4}]}))
    items = list(external_masks(tmp_path, tuple(cams)))
    failures = [i for i in items if isinstance(i, ViewFailure)]
    assert sorted(f.reason.split(" (")[0] for f in failures) == ["camera pose or intrinsics are not finite",
                                                                 "no camera for image stem '9999'"]
    first = next(i for i in items if isinstance(i, ViewMasks) and i.view == 0)
    assert first.segments[1] == Segment(1, None, "mug", 0.9) and first.segments[3].score == 0.4
    proposals, rejected = lift_view(plane_caster(), cams[0], first, CONFIG)
    assert [p.label for p in proposals] == [1]
    assert rejected[0]["label"] == 3 and "has no pixels" in rejected[0]["reason"]


def test_external_json_errors_name_the_field(tmp_path):
    cams = ring(1, 1.0, 0.8, width=40, height_px=30)
    write_png(tmp_path / "0000.png", np.zeros((30, 40), np.uint16))
    (tmp_path / "0000.json").write_text(json.dumps({"segments": [{"label": 1, "score": 2.0}]}))
    (failure,) = list(external_masks(tmp_path, tuple(cams)))
    assert "segments[0].score: 2.0 (expected a number in [0, 1])" in failure.reason
    with pytest.raises(SceneInputError, match="folder not found"):
        list(external_masks(tmp_path / "nope", tuple(cams)))


def test_scannetpp_annotations_become_masks_of_the_scan(tmp_path):
    from phirie_jax.observe.masks import projected_masks, scannetpp_vertex_labels

    table = trimesh.creation.box(extents=[1.0, 1.0, 0.02])
    table.apply_translation([0, 0, -0.01])
    box = trimesh.creation.box(extents=[0.2, 0.2, 0.2])
    box.apply_translation([0, 0, 0.1])
    scan = trimesh.util.concatenate([table, box])
    # segments: table vertices → segment 5, box vertices → segment 9; object 0 (a "crate") is segment 9
    seg_indices = [5] * len(table.vertices) + [9] * len(box.vertices)
    (tmp_path / "segments.json").write_text(json.dumps({"segIndices": seg_indices}))
    anno = tmp_path / "segments_anno.json"
    anno.write_text(json.dumps({"segGroups": [{"objectId": 0, "label": "crate", "segments": [9]}]}))
    labels, names = scannetpp_vertex_labels(anno, len(scan.vertices))
    assert names == {1: "crate"} and np.all(labels[len(table.vertices):] == 1) and np.all(labels[:8] == 0)
    cams = ring(3, 1.0, 0.8, width=40, height_px=30, focal=35.0)
    caster = Raycaster(scan.vertices, scan.faces)
    for cam, masks in zip(cams, projected_masks(caster, labels, tuple(cams), names)):
        on_box = Raycaster(box.vertices, box.faces).depth_map(cam) > 0
        assert masks.segments == {1: Segment(1, 1, "crate")}
        np.testing.assert_array_equal(masks.labels == 1, on_box)
    with pytest.raises(SceneInputError, match=r"segIndices: 16 entries \(expected one per scan mesh vertex, 17\)"):
        scannetpp_vertex_labels(anno, len(scan.vertices) + 1)


def test_silhouette_votes_count_own_label_and_none_and_abstain_elsewhere():
    from phirie_jax.observe.lift import silhouette_votes

    cam = ring(1, 1.0, 0.0, width=40, height_px=30, focal=35.0)[0]
    labels = np.zeros((30, 40), np.int64)
    labels[:, :20] = 5          # the instance's half of the image
    labels[:, 30:] = 9          # another instance: abstains
    cols = np.array([5.5, 25.5, 35.5])
    # points 0.5 m in front of the camera through pixel (col, 15.5), and one behind it
    rays = np.stack([cols, np.full(3, 15.5), np.ones(3)], 1) @ np.linalg.inv(cam.K).T
    in_front = cam.center + 0.5 * rays @ cam.camera_to_world[:3, :3].T
    behind = cam.center - 0.5 * (rays[:1] @ cam.camera_to_world[:3, :3].T)
    (on, counted), (on_other, counted_other) = silhouette_votes(
        [np.concatenate([in_front, behind]), in_front], [5, 9], cam, labels)
    np.testing.assert_array_equal(on, [True, False, False, False])
    np.testing.assert_array_equal(counted, [True, True, False, False])
    np.testing.assert_array_equal(on_other, [False, False, True])
    np.testing.assert_array_equal(counted_other, [False, True, True])
