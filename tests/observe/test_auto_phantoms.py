"""Automatic discovery on a rough, optimiser-shaped tabletop: floor bumps 1–2 cm tall, floaters,
a support that is not flat, and supports found from positions alone (per-sample normals
scrambled, as on a real capture's splat-derived surface). Geometry of the synthetic ``tiny``
preset as a scan mesh (no splat rendering), so it runs in seconds."""

from __future__ import annotations

import numpy as np
import pytest

from phirie_jax.observe.auto import Samples, observed_samples, segment
from phirie_jax.observe.config import AutoMaskConfig
from phirie_jax.observe.evaluate import iou_matrix, match
from phirie_jax.observe.raycast import Raycaster
from phirie_jax.observe.support_fit import frame_support_plane
from tests.observe.helpers import ring

TABLE_Z = 0.75


def _bump(centre, radius, height):
    import trimesh

    dome = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    dome.vertices *= [radius, radius, height]
    dome.vertices[:, 2] = np.maximum(dome.vertices[:, 2], 0.0)
    dome.apply_translation([centre[0], centre[1], TABLE_Z])
    return dome


@pytest.fixture(scope="module")
def rough_tabletop():
    import trimesh

    from phirie_jax.synthetic import build_scene

    scene = build_scene("tiny", 0)
    rng = np.random.default_rng(0)
    table = scene.furniture.table.copy()
    top = np.abs(table.vertices[:, 2] - TABLE_Z) < 1e-6
    table = table.subdivide_to_size(0.02)
    top = np.abs(table.vertices[:, 2] - TABLE_Z) < 1e-6
    table.vertices[top, 2] += rng.normal(0, 0.002, top.sum())   # a rough, not flat, tabletop
    centres = [o.pose[:2, 3] for o in scene.objects]
    bumps, xy = [], []
    while len(bumps) < 4:
        c = rng.uniform(-0.45, 0.45, 2) * [1.0, 0.6]
        if all(np.linalg.norm(c - p) > 0.16 for p in centres + xy):
            bumps.append(_bump(c, rng.uniform(0.025, 0.04), rng.uniform(0.01, 0.02)))
            xy.append(c)
    floaters = [trimesh.creation.icosphere(2, 0.02).apply_translation([*rng.uniform(-0.3, 0.3, 2), z])
                for z in (0.9, 1.0, 1.1)]
    parts = [scene.furniture.floor, table, *bumps, *floaters, *[o.world_mesh() for o in scene.objects]]
    mesh = trimesh.util.concatenate(parts)
    cams = ring(12, 0.9, 1.45, target=(0.0, 0.0, 0.78), width=160, height_px=120, focal=144.0)
    return scene, Raycaster(mesh.vertices, mesh.faces), cams


def _scrambled(samples: Samples, seed=0) -> Samples:
    """The samples with random normals: no support can come from normals."""
    n = np.random.default_rng(seed).normal(size=samples.normals.shape)
    return Samples(samples.points, n / np.linalg.norm(n, axis=1, keepdims=True), samples.hit_sample,
                   samples.hit_camera, samples.cameras)


def test_bumps_and_floaters_are_not_objects_and_supports_need_no_normals(rough_tabletop):
    scene, caster, cams = rough_tabletop
    config = AutoMaskConfig()
    samples = _scrambled(observed_samples(caster, cams, config.sample_stride, config.sample_voxel))
    seg = segment(samples, np.array([0.0, 0.0, 1.0]), config, cams, caster)
    assert any(abs(s.offset - TABLE_Z) < 0.005 for s in seg.supports)
    truth = [o.world_mesh().sample(2000, seed=0) for o in scene.objects]
    clusters = [samples.points[seg.labels == o["id"]] for o in seg.objects]
    assert len(seg.objects) == len(scene.objects)                                  # no phantom
    assert len(match(iou_matrix(truth, clusters, voxel=0.02), 0.3)) == len(scene.objects)  # every object
    reasons = " ".join(r["reason"] for r in seg.rejected)
    assert "a bump of the support" in reasons


def test_clusters_seen_by_few_of_the_views_that_look_at_them_are_rejected(rough_tabletop):
    _, caster, cams = rough_tabletop
    samples = observed_samples(caster, cams, 2, 0.005)
    strict = segment(samples, np.array([0.0, 0.0, 1.0]), AutoMaskConfig(min_views=len(cams) + 1), cams, caster)
    assert strict.objects == [] and all("min_views" in r["reason"] for r in strict.rejected if "views" in r)
    # each object's views are counted and no object is seen by fewer than half the views facing it
    seg = segment(samples, np.array([0.0, 0.0, 1.0]), AutoMaskConfig(), cams, caster)
    assert all(o["views"] >= 0.5 * o["looking_views"] and o["views"] >= 3 for o in seg.objects)


def test_the_frame_support_plane_seeds_discovery(rough_tabletop):
    scene, caster, cams = rough_tabletop
    samples = observed_samples(caster, cams, 2, 0.005)
    seed = frame_support_plane({"support": {"normal": [0.0, 0.0, 2.0], "offset": 2 * TABLE_Z}})
    np.testing.assert_allclose(seed[0], [0, 0, 1]) and np.testing.assert_allclose(seed[1], TABLE_Z)
    seg = segment(samples, np.array([0.0, 0.0, 1.0]), AutoMaskConfig(), cams, caster, seeds=(seed,))
    assert seg.supports[0].source == "frame" and abs(seg.supports[0].offset - TABLE_Z) < 0.005
    assert len(seg.objects) == len(scene.objects)
    # a seed no surface holds is recorded and discovery goes on with its own fit
    seg = segment(samples, np.array([0.0, 0.0, 1.0]), AutoMaskConfig(), cams, caster,
                  seeds=((np.array([0.0, 0.0, 1.0]), 0.3),))
    assert seg.planes[0]["source"] == "frame" and seg.planes[0]["reason"]
    assert any(abs(s.offset - TABLE_Z) < 0.005 for s in seg.supports)


def test_frame_support_plane_from_the_frame_record():
    assert frame_support_plane(None) is None and frame_support_plane({"support": "x"}) is None
    normal, offset = frame_support_plane({"support": {"normal": [0, 0, -1], "point": [0, 0, 0.4]}})
    np.testing.assert_allclose(normal, [0, 0, 1]) and np.testing.assert_allclose(offset, 0.4)
    # as the frame stage records it (SupportPlane.record: normal · x = height)
    normal, offset = frame_support_plane({"support": {"normal": [0.0, 0.6, 0.8], "height": 0.5,
                                                      "point": [0.0, 0.3, 0.4], "source": "splat surface"}})
    np.testing.assert_allclose(normal, [0, 0.6, 0.8]) and np.testing.assert_allclose(offset, 0.5)
    assert frame_support_plane({"support": None, "up_source": "given (--up +z)"}) is None
    # the evidence plane the up came from, moved into the world by capture_to_world (x_w = 2 R x_c)
    rot = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])   # capture +y → world +z
    c2w = np.eye(4)
    c2w[:3, :3] = 2 * rot
    record = {"capture_to_world": c2w.tolist(), "up_source": "support plane (1 parallel plane(s), ...)",
              "evidence": {"planes": [{"normal": [0, 1, 0], "offset": 0.3, "inliers": 50},
                                      {"normal": [1, 0, 0], "offset": 1.0, "inliers": 90}]}}
    normal, offset = frame_support_plane(record)
    np.testing.assert_allclose(normal, [0, 0, 1], atol=1e-12) and np.testing.assert_allclose(offset, 0.6)
    assert frame_support_plane({**record, "up_source": "given (--up +y)"}) is None


def test_automatic_instances_supported_by_few_views_are_rejected():
    """After association: the issue's phantoms were supported by 4-8 of 36 views (confidence
    0.36-0.50); the true objects by most of the views that have them in the image."""
    from phirie_jax.observe.config import ObserveConfig
    from phirie_jax.observe.stage import _seen_too_little

    config = ObserveConfig()
    assert "min_views" in _seen_too_little({"views": [0, 1], "confidence": 1.0}, config)
    assert "min_view_fraction" in _seen_too_little({"views": list(range(6)), "confidence": 0.36}, config)
    assert _seen_too_little({"views": list(range(30)), "confidence": 0.83}, config) is None


@pytest.mark.slow
def test_splatted_bumps_and_floaters_make_no_instance(tmp_path):
    """End to end on Gaussians: the tiny preset's capture with four 1-2 cm floor bumps and four
    floater clouds added (``synthetic.artefacts``), converted as a user's capture (no scan, no
    masks) with ``--masks auto``: the instances are the true objects, none lies on an artefact,
    and no object is kept that is not a true one."""
    import json
    import shutil

    from phirie_jax.pipeline import run_convert
    from phirie_jax.synthetic.artefacts import add_artefacts
    from phirie_jax.synthetic.scene import synthesize

    scene_dir = tmp_path / "scene"
    synthesize(scene_dir, "tiny", 0)
    artefacts = add_artefacts(scene_dir, 0)
    capture = tmp_path / "capture"
    shutil.copytree(scene_dir, capture, ignore=shutil.ignore_patterns("surface.ply", "masks", "gt"))
    manifest = run_convert(capture, tmp_path / "out", masks="auto", stages=("observe", "objects"))
    truth = np.array([np.asarray(o["pose"])[:2, 3] for o in json.loads((scene_dir / "gt" / "objects.json").read_text())])
    centres = {i["id"]: np.mean(i["bounds"], axis=0)[:2] for i in manifest["instances"]}
    # one instance per true object, each over it (the 128x96 views lift too sparse a Q for the 1 cm IoU)
    nearest = {k: int(np.argmin(np.linalg.norm(truth - c, axis=1))) for k, c in centres.items()}
    assert len(centres) == len(truth) and sorted(nearest.values()) == list(range(len(truth)))
    assert all(np.linalg.norm(truth[nearest[k]] - c) < 0.05 for k, c in centres.items())
    assert all(np.linalg.norm(np.asarray(a["centre"][:2]) - c) > 0.05 for a in artefacts for c in centres.values())
    kept = [o for o in manifest["objects"] if o["status"] in ("accepted", "unverified")]
    assert all(o["id"] in centres for o in kept)   # no phantom became a body


def test_what_stands_above_the_support_and_is_no_object_is_unknown_in_the_masks(rough_tabletop):
    """Floaters and bumps are UNKNOWN in the masks (they may hide an object: no carving behind
    them), the table is 0, every object keeps its label, and UNKNOWN is never a segment."""
    from phirie_jax.observe.auto import UNKNOWN, auto_masks

    scene, caster, cams = rough_tabletop
    config = AutoMaskConfig()
    samples = observed_samples(caster, cams, config.sample_stride, config.sample_voxel)
    seg = segment(samples, np.array([0.0, 0.0, 1.0]), config, cams, caster)
    assert seg.unknown is not None and not (seg.unknown & (seg.labels > 0)).any()
    boxes = [o.world_mesh().bounds for o in scene.objects]
    floater_hits, table_hits = [], []
    for view in auto_masks(caster, tuple(cams), seg, config.sample_voxel):
        present = set(np.unique(view.labels).tolist())
        assert UNKNOWN not in view.segments and set(view.segments) == present - {0, UNKNOWN}
        hits, _, _ = caster.cast_camera(cams[view.view])
        points, labels = hits.points[hits.hit], view.labels.ravel()[hits.hit]
        near_object = np.zeros(len(points), bool)
        for lo, hi in boxes:
            near_object |= ((points > lo - 0.03) & (points < hi + 0.03)).all(1)
        floater_hits.append(labels[(points[:, 2] > TABLE_Z + 0.1) & ~near_object])
        table_hits.append(labels[(np.abs(points[:, 2] - TABLE_Z) < 0.004) & ~near_object
                                 & (np.abs(points[:, :2]) < 0.3).all(1)])
    floater_hits, table_hits = np.concatenate(floater_hits), np.concatenate(table_hits)
    assert len(floater_hits) > 100 and (floater_hits == UNKNOWN).mean() > 0.9
    assert len(table_hits) > 1000 and (table_hits == 0).mean() > 0.9
