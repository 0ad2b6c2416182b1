"""run_observe end to end on a small tabletop folder (geometry of the synthetic ``tiny``
preset, masks projected from the ground-truth meshes, no splat rendering), automatic
discovery on the same geometry, and the manifest API."""

from __future__ import annotations

import json

import numpy as np
import pytest

from phirie_jax.errors import SceneInputError
from phirie_jax.manifest import SCHEMA, Manifest
from phirie_jax.observe.auto import observed_samples, segment
from phirie_jax.observe.config import AutoMaskConfig, ObserveConfig
from phirie_jax.observe.evaluate import aabb_iou, evaluate, iou_matrix, match
from phirie_jax.observe.raycast import Raycaster
from phirie_jax.observe.stage import run_observe
from tests.observe.helpers import ground_truth_ids, tabletop_folder, write_png

TABLE_Z = 0.75
TINY = ObserveConfig(pixel_stride=1, mask_erosion_px=1)


@pytest.fixture(scope="module")
def tabletop(tmp_path_factory):
    root = tmp_path_factory.mktemp("tabletop")
    scene, cams, _masks = tabletop_folder(root)
    return root, scene, cams


@pytest.fixture(scope="module")
def observed(tabletop, tmp_path_factory):
    root, _, _ = tabletop
    out = tmp_path_factory.mktemp("out")
    return out, run_observe(root, out, TINY, masks="files")


def test_mask_files_give_one_instance_per_object_with_its_id(tabletop, observed):
    root, scene, _cams = tabletop
    out, manifest = observed
    assert manifest["schema"] == SCHEMA
    assert [i["id"] for i in manifest["instances"]] == ground_truth_ids(root)
    on_disk = json.loads((out / "manifest.json").read_text())
    assert on_disk["instances"] == manifest["instances"]
    for inst, obj in zip(manifest["instances"], scene.objects):
        assert set(inst) >= {"id", "category", "views", "num_points", "bounds", "source", "points"}
        assert inst["source"] == "files" and len(inst["views"]) >= 2
        data = np.load(out / inst["points"])
        q = data["points"]
        assert q.shape == (inst["num_points"], 3) and q.dtype == np.float32
        np.testing.assert_allclose(inst["bounds"], [q.min(0), q.max(0)], atol=1e-6)
        # Q_i lies on the object: within a few mm of its mesh, and covers it
        import trimesh

        _, dist, _ = trimesh.proximity.closest_point(obj.world_mesh(), q)
        assert np.percentile(dist, 95) < 0.005
        assert set(data["views"].tolist()) == set(inst["views"]) and np.all(data["labels"] == obj.id)
        assert data["bboxes"].shape == (len(data["views"]), 4) and np.all(data["pixels"] > 0)
    for stage in ("observe", "observe.surface", "observe.masks", "observe.lift", "observe.associate"):
        assert manifest["timings"][stage] >= 0
    assert manifest["observe"]["surface"]["kind"] == "scan"


def test_evaluation_scores_the_instances(tabletop, observed):
    root, _, cams = tabletop
    out, _ = observed
    result = evaluate(root, out, cams)
    assert result["recall"] == 1.0 and result["precision"] == 1.0
    assert all(o["best_iou"] >= 0.5 for o in result["per_object"])


def test_rerun_keeps_other_sections_and_replaces_instances(tabletop, observed, tmp_path):
    root, _, _ = tabletop
    manifest = Manifest.load_or_create(tmp_path)
    manifest.set("objects", [{"id": 1, "status": "accepted"}])
    manifest.record_timing("construct", 1.5)
    manifest.write()
    first = run_observe(root, tmp_path, TINY, masks="files")
    second = run_observe(root, tmp_path, TINY, masks="files")
    assert [{k: o[k] for k in ("id", "status")} for o in second["objects"]] == [{"id": 1, "status": "accepted"}]
    assert second["timings"]["construct"] == 1.5
    assert second["instances"] == first["instances"]  # deterministic


def test_automatic_masks_find_the_objects(tabletop, tmp_path):
    root, _scene, cams = tabletop
    manifest = run_observe(root, tmp_path, TINY, masks="auto")
    auto = manifest["observe"]["auto"]
    assert [round(s["offset"], 3) for s in auto["supports"]][:2] == [0.0, TABLE_Z] or \
        sorted(round(s["offset"], 3) for s in auto["supports"]) == [0.0, TABLE_Z]
    result = evaluate(root, tmp_path, cams)
    assert result["recall"] == 1.0 and result["precision"] == 1.0
    assert (tmp_path / "observe" / "masks" / cams[0].name).is_file()


def test_supports_and_clusters_on_the_scan(tabletop):
    import trimesh

    root, scene, cams = tabletop
    mesh = trimesh.load(root / "surface.ply", process=False)
    caster = Raycaster(mesh.vertices, mesh.faces)
    config = AutoMaskConfig()
    samples = observed_samples(caster, cams, 1, config.sample_voxel)
    seg = segment(samples, np.array([0.0, 0.0, 1.0]), config, cams, caster)
    points = samples.points
    assert len(seg.objects) == len(scene.objects)
    truth = [obj.world_mesh().sample(2000, seed=0) for obj in scene.objects]
    clusters = [points[seg.labels == o["id"]] for o in seg.objects]
    assert len(match(iou_matrix(truth, clusters, voxel=0.02), 0.3)) == len(scene.objects)


def test_external_folder_with_per_view_labels(tabletop, tmp_path):
    """The same masks as an external segmenter would give them: labels shuffled per image."""
    import cv2

    root, scene, cams = tabletop
    folder = tmp_path / "sam"
    rng = np.random.default_rng(5)
    for cam in cams:
        mask = cv2.imread(str(root / "masks" / cam.name), cv2.IMREAD_UNCHANGED).astype(np.int64)
        perm = np.concatenate([[0], rng.permutation(np.arange(1, 20))])
        write_png(folder / cam.name, perm[mask].astype(np.uint16))
        segs = [{"label": int(k), "score": 0.8, "category": "thing"} for k in np.unique(perm[mask]) if k]
        (folder / cam.name).with_suffix(".json").write_text(json.dumps({"segments": segs}))
    out = tmp_path / "out"
    manifest = run_observe(root, out, TINY, masks=folder)
    assert len(manifest["instances"]) == len(scene.objects)
    assert all(i["source"] == "external" and i["category"] == "thing" for i in manifest["instances"])
    assert evaluate(root, out, cams)["recall"] == 1.0


def test_wrong_size_mask_file_is_a_clear_error(tabletop, tmp_path):
    import shutil

    root, _, cams = tabletop
    bad = tmp_path / "scene"
    shutil.copytree(root, bad)
    write_png(bad / "masks" / cams[3].name, np.zeros((10, 10), np.uint16))
    with pytest.raises(SceneInputError, match=f"{cams[3].name}: mask size: 10×10"):
        run_observe(bad, tmp_path / "out", TINY, masks="files")


def test_no_masks_for_files_mode_is_a_clear_error(tabletop, tmp_path):
    import shutil

    root, _, _ = tabletop
    bare = tmp_path / "scene"
    shutil.copytree(root, bare, ignore=shutil.ignore_patterns("masks"))
    with pytest.raises(SceneInputError, match="--masks files: no masks/ folder"):
        run_observe(bare, tmp_path / "out", TINY, masks="files")


def test_manifest_api(tmp_path):
    manifest = Manifest.load_or_create(tmp_path)
    manifest.set("instances", [{"id": 2, "bounds": np.zeros((2, 3))}])
    manifest.upsert("objects", [{"id": 3, "status": "failed"}, {"id": 1, "status": "accepted"}])
    manifest.upsert("objects", [{"id": 3, "status": "accepted", "mass": np.float32(0.25)}])
    with manifest.timed("stage"):
        pass
    manifest.write()
    assert [p.name for p in tmp_path.iterdir()] == ["manifest.json"]  # no temporary left behind
    data = json.loads((tmp_path / "manifest.json").read_text())
    assert next(iter(data)) == "schema" and data["schema"] == SCHEMA
    assert [{k: o[k] for k in ("id", "status", "mass")} for o in data["objects"]] == [
        {"id": 1, "status": "accepted", "mass": None}, {"id": 3, "status": "accepted", "mass": 0.25}]
    assert data["instances"][0]["bounds"] == [[0.0] * 3] * 2 and data["timings"]["stage"] >= 0
    with pytest.raises(ValueError):
        manifest.set("timings", {})
    (tmp_path / "manifest.json").write_text(json.dumps({"schema": "phirie/0"}))
    with pytest.raises(SceneInputError, match="manifest.json: schema: 'phirie/0' \\(expected 'phirie/1'\\)"):
        Manifest.load_or_create(tmp_path)


def test_bleeding_mask_edges_do_not_grow_the_instance_bounds(tabletop, tmp_path):
    """Masks grown by 2 px past the silhouettes (a segmenter's bleeding edge) lift a ring of
    table around each object. The silhouette check and the support clearance drop it: AABB IoU
    of the instance bounds with the true object ≥ 0.5 (< 0.5 for some object with both off)."""
    import shutil

    import cv2

    root, scene, cams = tabletop
    bled = tmp_path / "scene"
    shutil.copytree(root, bled)
    for cam in cams:
        mask = cv2.imread(str(root / "masks" / cam.name), cv2.IMREAD_UNCHANGED)
        grown = cv2.dilate(mask, np.ones((5, 5), np.uint8))
        write_png(bled / "masks" / cam.name, np.where(mask > 0, mask, grown).astype(np.uint16))
    truth = {o.id: o.world_mesh().bounds for o in scene.objects}
    runs = {"off": dict(silhouette_agreement=0.0, support_clearance=None),
            "silhouette only": dict(support_clearance=None), "default": {}}
    ious, dropped = {}, {}
    for name, options in runs.items():
        config = ObserveConfig(pixel_stride=1, mask_erosion_px=0, **options)
        manifest = run_observe(bled, tmp_path / name.replace(" ", "_"), config, masks="files")
        assert sorted(i["id"] for i in manifest["instances"]) == sorted(truth)
        ious[name] = {i["id"]: aabb_iou(i["bounds"], truth[i["id"]]) for i in manifest["instances"]}
        dropped[name] = [i["points_dropped"] for i in manifest["instances"]]
        assert all(i["support"]["source"] == "surface" for i in manifest["instances"])
    assert min(ious["off"].values()) < 0.5                    # the defect is there without the checks
    assert all(d["outside_silhouette"] == 0 and d["on_support"] == 0 for d in dropped["off"])
    assert all(d["outside_silhouette"] > 0 for d in dropped["silhouette only"])
    assert sum(ious["silhouette only"].values()) > sum(ious["off"].values())
    assert min(ious["default"].values()) >= 0.5
    assert all(d["on_support"] > 0 for d in dropped["default"])
