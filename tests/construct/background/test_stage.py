"""run_background end to end on a toy scene (``background_scene``): coupled removal, the occlusion
test, composite targets, the fill recovering the plane's colour, an unsupported region, a
rejected object kept, the manifest contract and the output file."""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest

from phirie_jax.construct.background.config import BackgroundConfig, CropConfig, RefineConfig, RemovalConfig
from phirie_jax.construct.background.removal import load_object, mask_votes
from phirie_jax.construct.background.stage import run_background
from phirie_jax.construct.background.views import CropRenderer
from phirie_jax.errors import SceneInputError
from phirie_jax.io.ply import read_gaussian_ply
from phirie_jax.io.scene import load_scene
from phirie_jax.records import InstanceRecord, ObjectRecord
from tests.construct.background import scene as toy

FAST = BackgroundConfig(crops=CropConfig(target_sizes=(64,), mask_sizes=(32, 64), margin_px=4),
                        refine=RefineConfig(iterations=12), removal=RemovalConfig(mask_views=6))
FILL_TOL = 0.12      # mean |colour − orange| over the hidden patches, seen from above
HOLE_ERROR = 0.25    # ... which, with the objects only removed, shows the background through the plane
OBJECT_COLOUR_DIST = 0.25  # no target pixel may be this close to a removed object's colour


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    scene = toy.build(tmp_path_factory.mktemp("toy"))
    manifest = run_background(scene.root / "scene", scene.out, FAST)
    return scene, manifest


def _kept_mask(scene, manifest):
    from scipy.spatial import cKDTree

    out = read_gaussian_ply(scene.out / "background.ply")
    kept = out.means[: out.num - manifest["background"]["filled"]]
    d, _ = cKDTree(kept).query(scene.data.means)
    return d < 1e-7, out


def test_manifest_contract_and_output_file(run):
    scene, manifest = run
    b = manifest["background"]
    assert json.loads((scene.out / "manifest.json").read_text())["background"] == b
    assert b["path"] == "background.ply" and (scene.out / b["path"]).is_file()
    out = read_gaussian_ply(scene.out / b["path"])
    assert out.num == scene.data.num - b["removed"] + b["filled"]
    assert out.sh.shape[1] == scene.data.sh.shape[1]  # same SH degree as the capture
    status = {o["id"]: o["status"] for o in b["objects"]}
    assert status == {1: "filled", 2: "filled", 3: "skipped", 4: "unsupported", 5: "failed"}
    assert "not removed" in next(o for o in b["objects"] if o["id"] == 5)["reason"]
    for o in b["objects"]:
        if o["status"] not in ("skipped", "failed"):
            assert {"obs", "asset", "mask", "union"} <= set(o["removed"])
    assert {o["id"] for o in b["objects"] if o.get("primary_view")} == {1, 2}
    assert "background" in manifest["timings"] and "background.refine" in manifest["timings"]


def test_a_scene_of_other_subset_sizes_compiles_nothing_new(run, tmp_path):
    """Every render and the fit take bucketed shapes: a second scene whose objects' subsets differ
    in size (plane Gaussians dropped), but not its buckets, reuses every program of the first."""
    import shutil

    from phirie_jax.io.ply import write_gaussian_ply

    scene, manifest = run
    assert manifest["background"]["compiles"]["count"] > 0        # the first run compiled the stage's programs
    shutil.copytree(scene.root / "scene", tmp_path / "scene")
    shutil.copytree(scene.root / "out", tmp_path / "out", ignore=shutil.ignore_patterns("background*"))
    keep = np.ones(scene.data.num, bool)
    keep[np.flatnonzero(scene.labels == 0)[::97]] = False          # a few plane Gaussians fewer everywhere
    write_gaussian_ply(tmp_path / "scene" / "point_cloud.ply", scene.data.subset(keep))
    second = run_background(tmp_path / "scene", tmp_path / "out", FAST)["background"]
    assert second["source_gaussians"] < manifest["background"]["source_gaussians"]
    assert second["compiles"]["count"] == 0, second["compiles"]


def test_kept_gaussians_are_written_unchanged(run):
    scene, manifest = run
    kept, out = _kept_mask(scene, manifest)
    n_kept = out.num - manifest["background"]["filled"]
    src = scene.data.subset(np.flatnonzero(kept))
    for field in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(out, field)[:n_kept], getattr(src, field))


def test_removal_takes_the_objects_and_only_what_the_radii_allow(run):
    from scipy.spatial import cKDTree

    scene, manifest = run
    kept, _ = _kept_mask(scene, manifest)
    labels = scene.labels
    for k in (1, 2, 4):
        assert not kept[labels == k].any(), f"object {k} left ghosts"
    assert kept[labels == 3].all()            # rejected: stays in the background
    assert kept[labels == toy.DISTRACTOR].all()  # inside object 4's bounds, occluded in its masks
    collateral = ~kept & (labels == 0)
    centres = np.array([toy.SPHERES[k][0] for k in (1, 2)])
    radii = np.array([toy.SPHERES[k][1] for k in (1, 2)])
    d, nearest = cKDTree(centres).query(scene.data.means[collateral])
    assert np.all(d - radii[nearest] <= FAST.removal.obs_radius + 1e-6)  # only the plane next to a removed object
    floating = next(o for o in manifest["background"]["objects"] if o["id"] == 4)
    assert floating["removed"]["union"] == int(np.sum(labels == 4))  # exactly that object


def test_the_occlusion_test_is_what_keeps_the_distractors(run):
    scene, manifest = run
    inst = {i["id"]: InstanceRecord.from_json(i) for i in manifest["instances"]}
    entry = next(ObjectRecord.from_json(o) for o in manifest["objects"] if o["id"] == 4)
    obj = load_object(entry, inst[4], scene.out)
    cams = load_scene(scene.root / "scene", check_images=False).cameras
    distractors = set(np.flatnonzero(scene.labels == toy.DISTRACTOR))
    crops = CropRenderer()
    one_vote = dataclasses.replace(FAST, removal=dataclasses.replace(FAST.removal, mask_votes=1))
    with_test, record, _ = mask_votes(scene.data, [obj], cams, one_vote, crops)
    no_test = dataclasses.replace(one_vote, removal=dataclasses.replace(one_vote.removal, occlusion_tolerance=1e9))
    without, _, _ = mask_votes(scene.data, [obj], cams, no_test, crops)
    assert not distractors & set(with_test[0])
    assert distractors & set(without[0]), "no distractor is ever behind the sphere: the toy lost its teeth"
    assert record[0]["occluded_rejected"] >= 0


def test_unsupported_region_is_recorded_not_fatal(run):
    _, manifest = run
    b = manifest["background"]
    entry = next(u for u in b["unsupported_regions"] if u["id"] == 4)
    assert entry["reason"] and entry["removed"] > 0
    assert b["failed_completions"] == []


def test_targets_composite_every_removed_object(run):
    scene, manifest = run
    folder = scene.out / manifest["background"]["targets"]["folder"]
    colours = np.array([toy.COLOURS[k] for k in (1, 2, 4)])
    checked = 0
    for frame in manifest["background"]["targets"]["frames"]:
        stem = frame["name"].rsplit(".", 1)[0]
        target = cv2.imread(str(folder / f"{stem}.png"))[..., ::-1] / 255.0
        mask = cv2.imread(str(folder / f"{stem}_mask.png"), cv2.IMREAD_UNCHANGED) > 0
        pixels = target[mask]
        checked += len(pixels)
        dist = np.linalg.norm(pixels[:, None] - colours[None], axis=-1)
        assert dist.min() > OBJECT_COLOUR_DIST, f"a removed object shows in the target of {frame['name']}"
    assert checked > 100


def test_fill_recovers_the_plane_colour_under_the_objects(run):
    import jax.numpy as jnp

    from phirie_jax.io.camera import intrinsics_matrix
    from phirie_jax.render import render
    from phirie_jax.synthetic.scene import look_at
    from phirie_jax.types import Camera

    scene, manifest = run
    kept, out = _kept_mask(scene, manifest)
    cam = Camera("top", intrinsics_matrix(200.0, 200.0, 48, 48), look_at(np.array([0.0, -0.05, 0.6]),
                 np.array([0.0, 0.0, 0.0]), up=(0.0, 1.0, 0.0)), 96, 96)
    bg = jnp.asarray(toy.BACKGROUND_RGB, jnp.float32)
    filled = np.asarray(render(out.to_kernel(), cam, background=bg).rgb)
    removed_only = np.asarray(render(scene.data.subset(np.flatnonzero(kept)).to_kernel(), cam, background=bg).rgb)
    # pixels over the never-seen contact patches of objects 1 and 2
    uv, _ = cam.project(np.array([[*toy.SPHERES[k][0][:2], 0.0] for k in (1, 2)]))
    errors_fill, errors_hole = [], []
    for (u, v), k in zip(uv, (1, 2)):
        half = max(1, int(0.3 * toy.SPHERES[k][1] * 200 / 0.6))
        patch = (slice(int(v) - half, int(v) + half + 1), slice(int(u) - half, int(u) + half + 1))
        errors_fill.append(np.abs(filled[patch] - toy.ORANGE).mean())
        errors_hole.append(np.abs(removed_only[patch] - toy.ORANGE).mean())
    assert min(errors_hole) > HOLE_ERROR  # without the fill the hole shows
    assert max(errors_fill) < FILL_TOL, errors_fill


def test_the_cameras_see_through_no_cell_of_a_whole_table(run):
    """The toy's plane runs past every object's fill: every view that holds a cell sees it on the
    plane or hidden, none past it, so no cell is dropped."""
    _, manifest = run
    for o in manifest["background"]["objects"]:
        if o["id"] in (1, 2):
            record = o["fill"]["see_through"]
            assert record["views"] > 0 and record["dropped"] == 0, record
            assert o["fill"]["disks"] == record["cells"]


def test_a_missing_objects_section_is_an_error_for_people(tmp_path):
    (tmp_path / "manifest.json").write_text(json.dumps({"schema": "phirie/1", "timings": {}, "instances": []}))
    with pytest.raises(SceneInputError, match="objects"):
        run_background(tmp_path, tmp_path, FAST)


@pytest.mark.parametrize("support_source, hits", [("surface", 400), ("surface", 4), ("observed points", 0)])
def test_a_semi_transparent_tabletop_falls_back_to_the_observed_support(tmp_path, support_source, hits):
    """Optimizer-shaped captures describe a tabletop with semi-transparent Gaussians: too few
    opaque ones ring an object to fit its plane. A support plane observation found under it on
    the scene surface then gives the level plane; a support that is only Q's own base, or a few
    surface hits (a wall-mounted head's plaque), does not."""
    from phirie_jax.io.ply import write_gaussian_ply

    scene = toy.build(tmp_path)
    ply = scene.root / "scene" / "point_cloud.ply"
    data = read_gaussian_ply(ply)
    logits = data.opacity_logits.copy()
    logits[scene.labels == 0] = np.log(0.3 / 0.7)  # below PlaneConfig.min_opacity
    write_gaussian_ply(ply, dataclasses.replace(data, opacity_logits=logits))
    manifest = json.loads((scene.out / "manifest.json").read_text())
    for instance in manifest["instances"]:
        instance.get("support", {}).update(source=support_source, hits=hits)
    (scene.out / "manifest.json").write_text(json.dumps(manifest))

    b = run_background(scene.root / "scene", scene.out, FAST)["background"]
    records = {o["id"]: o for o in b["objects"]}
    if hits >= 20:
        for k in (1, 2):
            assert records[k].get("plane_source", "").startswith("observed support:"), (records[k], b["unsupported_regions"])
            assert records[k]["status"] == "filled" and records[k]["fill"]["disks"] > 0
            np.testing.assert_allclose(records[k]["plane"]["normal"], [0, 0, 1])
            assert abs(records[k]["plane"]["point"][2]) < 1e-9  # the recorded support height
        assert {u["id"] for u in b["unsupported_regions"]} == set()
    else:
        assert {u["id"] for u in b["unsupported_regions"]} >= {1, 2}
        assert all("plane_source" not in records[k] for k in (1, 2))
