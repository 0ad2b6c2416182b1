"""A synthesized scene folder reads back like a real capture, through the same loader."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from phirie_jax.cli import main
from phirie_jax.io.colmap import read_colmap_model
from phirie_jax.io.ply import read_gaussian_ply
from phirie_jax.io.scene import load_scene
from phirie_jax.io.transforms_json import read_transforms_json
from phirie_jax.synthetic import synthesize

MIN_OBJECT_PIXELS = 10  # every object of the tiny scene is visible in some view


@pytest.fixture(scope="module")
def tiny_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("tiny")
    scene = synthesize(out, preset="tiny", seed=5)
    return out, scene


def test_folder_has_every_contract_file(tiny_dir):
    out, scene = tiny_dir
    for rel in ("point_cloud.ply", "transforms.json", "sparse/0/cameras.txt", "sparse/0/images.txt",
                "sparse/0/points3D.txt", "surface.ply", "gt/objects.json", "gt/background.ply",
                "gt/labels.npy"):
        assert (out / rel).is_file(), rel
    objects = json.loads((out / "gt" / "objects.json").read_text())
    assert [o["id"] for o in objects] == [o.id for o in scene.objects]
    for o in objects:
        assert (out / o["mesh"]).is_file() and (out / o["canonical_mesh"]).is_file()
        assert np.asarray(o["pose"]).shape == (4, 4)
    assert not list(out.rglob("*.tmp")), "no temporary files left behind"


def test_loader_reads_it_as_colmap_and_both_camera_files_agree(tiny_dir):
    out, scene = tiny_dir
    loaded = load_scene(out)
    assert loaded.layout == "colmap" and loaded.surface_mesh.name == "surface.ply"
    assert loaded.gaussians.num == scene.capture.data.num and loaded.gaussians.sh_degree == 3
    assert len(loaded.cameras) == len(scene.cameras) and all(m is not None for m in loaded.masks)
    from_json = read_transforms_json(out / "transforms.json")
    from_colmap, points = read_colmap_model(out / "sparse" / "0")
    for a, b, c in zip(from_json, from_colmap, scene.cameras):
        assert a.name == b.name == c.name
        np.testing.assert_allclose(a.world_to_camera, c.world_to_camera, atol=1e-9)
        np.testing.assert_allclose(b.world_to_camera, c.world_to_camera, atol=1e-9)
        np.testing.assert_allclose(a.K, b.K, atol=1e-9)
    assert points is not None and len(points) > 1000
    labels = np.load(out / "gt" / "labels.npy")
    assert labels.shape == (loaded.gaussians.num,) and labels.dtype == np.uint16
    np.testing.assert_array_equal(read_gaussian_ply(out / "gt" / "background.ply").means,
                                  scene.background.data.means)


def test_masks_are_16_bit_ids_that_follow_the_objects(tiny_dir):
    out, scene = tiny_dir
    loaded = load_scene(out)
    seen = {}
    for cam, mask_path in zip(loaded.cameras, loaded.masks):
        mask = cv2.imread(str(mask_path), cv2.IMREAD_UNCHANGED)
        assert mask.dtype == np.uint16 and mask.shape == (cam.height, cam.width)
        for obj in scene.objects:
            pixels = np.argwhere(mask == obj.id)
            seen[obj.id] = seen.get(obj.id, 0) + len(pixels)
            if len(pixels) < MIN_OBJECT_PIXELS:
                continue
            # the mask's centroid is near the projection of the object's centre
            centre = obj.world_mesh().bounding_box.centroid[None]
            uv, depth = cam.project(centre)
            assert depth[0] > 0
            assert np.linalg.norm(pixels.mean(0)[::-1] + 0.5 - uv[0]) < 0.25 * cam.width
        assert set(np.unique(mask)) <= {0, *[o.id for o in scene.objects]}
    assert all(seen[o.id] >= MIN_OBJECT_PIXELS for o in scene.objects), seen


def test_cli_synth_render_and_info(tmp_path, tiny_dir, capsys):
    out, _ = tiny_dir
    image = tmp_path / "view.png"
    assert main(["render", str(out), "--camera", "2", "--out", str(image), "--width", "64"]) == 0
    rendered = cv2.imread(str(image))
    assert rendered.shape == (48, 64, 3) and rendered.std() > 5
    assert main(["render", str(out), "--camera", "99", "--out", str(image)]) == 2
    assert "--camera: 99 (expected 0..11)" in capsys.readouterr().err
    assert main(["info", str(out), "--json"]) == 0
    facts = json.loads(capsys.readouterr().out)
    assert facts["masks"] == {"found": 12, "cameras": 12} and facts["surface_mesh"]["faces"] > 0


def test_cli_observe_finds_every_object_of_the_tiny_scene(tmp_path, tiny_dir, capsys):
    out, scene = tiny_dir
    assert main(["observe", str(out), "--out", str(tmp_path / "obs")]) == 0
    manifest = json.loads((tmp_path / "obs" / "manifest.json").read_text())
    assert manifest["schema"] == "phirie/1"
    assert sorted(i["id"] for i in manifest["instances"]) == [o.id for o in scene.objects]
    assert all(len(i["views"]) >= 2 for i in manifest["instances"])


def test_background_truth_is_the_capture_without_its_objects_plus_the_hidden_tabletop(tiny_dir):
    from phirie_jax.io.transforms_json import read_transforms_json
    from phirie_jax.render import render
    from phirie_jax.synthetic.truth import background_truth, uncovered_region

    out, scene = tiny_dir
    t = background_truth(out)
    assert t.labels.shape == (t.capture.num,) and t.hidden.shape == (t.truth.num,)
    # every background Gaussian of the capture is in the truth, no object Gaussian is
    from scipy.spatial import cKDTree

    d_bg, _ = cKDTree(t.truth.means).query(t.capture.means[t.labels == 0])
    d_obj, _ = cKDTree(t.truth.means).query(t.capture.means[t.labels > 0])
    assert d_bg.max() < 1e-6 and d_obj.min() > 1e-6
    # the hidden tabletop lies under the objects, at the table's height
    hidden = t.truth.means[t.hidden]
    assert len(hidden) > 0
    assert np.abs(hidden[:, 2] - scene.furniture.table_top_z).max() < 0.01
    camera = read_transforms_json(out / "transforms.json")[0]
    region = uncovered_region(t, camera, scene.config.background_rgb)
    assert 0 < region.sum() < region.size
    bg = np.asarray(scene.config.background_rgb, np.float32)
    before = np.asarray(render(t.capture.to_kernel(), camera, background=bg).rgb)
    after = np.asarray(render(t.truth.to_kernel(), camera, background=bg).rgb)
    changed = np.abs(before - after).max(-1) > 0.05
    assert changed[region].mean() > 0.5 and changed[~region].mean() < 0.01
