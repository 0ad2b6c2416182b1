"""Scene-folder detection and loading, and the one-line errors of ``phirie``."""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from phirie_jax.cli import main
from phirie_jax.errors import SceneInputError
from phirie_jax.io.camera import intrinsics_matrix
from phirie_jax.io.colmap import write_colmap_binary, write_colmap_text
from phirie_jax.io.ply import write_gaussian_ply
from phirie_jax.io.scene import load_scene
from phirie_jax.io.transforms_json import write_transforms_json
from phirie_jax.types import Camera, GaussianSplatData
from tests.conftest import shared_data

WIDTH, HEIGHT = 32, 24


def look_at(eye) -> np.ndarray:
    """World-to-camera (OpenCV) for a camera at ``eye`` looking at the origin, z up."""
    forward = -np.asarray(eye, float) / np.linalg.norm(eye)
    right = np.cross(forward, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rot = np.stack([right, down, forward])
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, -rot @ np.asarray(eye, float)
    return out


def make_cameras(n=3, model="PINHOLE", distortion=()) -> list[Camera]:
    return [
        Camera(name=f"{i:04d}.png", K=intrinsics_matrix(30.0, 30.0, WIDTH / 2, HEIGHT / 2),
               world_to_camera=look_at([2 * np.cos(i), 2 * np.sin(i), 1.0]), width=WIDTH,
               height=HEIGHT, model=model, distortion=np.asarray(distortion, float))
        for i in range(n)
    ]


def write_images(folder, cameras, size=(WIDTH, HEIGHT)):
    folder.mkdir(parents=True, exist_ok=True)
    for cam in cameras:
        cv2.imwrite(str(folder / cam.name), np.full((size[1], size[0], 3), 90, np.uint8))


def write_splat(path, n=100):
    rng = np.random.default_rng(0)
    write_gaussian_ply(path, GaussianSplatData(
        means=rng.uniform(-0.5, 0.5, (n, 3)).astype(np.float32),
        quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        log_scales=np.full((n, 3), -4, np.float32), opacity_logits=np.zeros(n, np.float32),
        sh=np.zeros((n, 16, 3), np.float32)))


@pytest.fixture
def colmap_scene(tmp_path_factory):
    tmp_path = tmp_path_factory.mktemp("colmap")
    cams = make_cameras()
    write_colmap_text(tmp_path / "sparse" / "0", cams)
    write_images(tmp_path / "images", cams)
    write_splat(tmp_path / "point_cloud" / "iteration_7000" / "point_cloud.ply", n=10)
    write_splat(tmp_path / "point_cloud" / "iteration_30000" / "point_cloud.ply", n=100)
    return tmp_path


@pytest.fixture
def nerfstudio_scene(tmp_path_factory):
    tmp_path = tmp_path_factory.mktemp("nerfstudio")
    cams = make_cameras(4)
    write_transforms_json(tmp_path / "transforms.json", cams)
    write_images(tmp_path / "images", cams)
    write_splat(tmp_path / "splat.ply", n=50)
    return tmp_path


def test_colmap_layout_picks_highest_iteration(colmap_scene):
    scene = load_scene(colmap_scene)
    assert scene.layout == "colmap" and len(scene.cameras) == 3
    assert scene.gaussians.num == 100 and scene.gaussians_path.parent.name == "iteration_30000"
    assert [c.name for c in scene.cameras] == sorted(c.name for c in scene.cameras)
    assert all(p.is_file() for p in scene.image_paths)
    assert scene.masks is None and scene.surface_mesh is None and scene.candidates == {}


def test_colmap_binary_in_sparse_root(tmp_path):
    cams = make_cameras()
    write_colmap_binary(tmp_path / "sparse", cams)
    write_images(tmp_path / "images", cams)
    scene = load_scene(tmp_path)
    assert scene.layout == "colmap" and scene.gaussians is None
    np.testing.assert_allclose(scene.cameras[1].world_to_camera, cams[1].world_to_camera, atol=1e-12)
    with pytest.raises(SceneInputError, match="no Gaussian PLY found"):
        scene.require_gaussians()


def test_nerfstudio_layout_matches_colmap_cameras(nerfstudio_scene):
    scene = load_scene(nerfstudio_scene)
    assert scene.layout == "nerfstudio" and scene.gaussians.num == 50
    for got, want in zip(scene.cameras, make_cameras(4)):
        assert got.name == want.name
        np.testing.assert_allclose(got.world_to_camera, want.world_to_camera, atol=1e-12)
        np.testing.assert_allclose(got.K, want.K, atol=1e-12)


def test_scannetpp_layout(tmp_path):
    cams = make_cameras(2)
    dslr = tmp_path / "dslr"
    write_transforms_json(dslr / "nerfstudio" / "transforms_undistorted.json", cams)
    write_images(dslr / "resized_undistorted_images", cams)
    meta = json.loads((dslr / "nerfstudio" / "transforms_undistorted.json").read_text())
    for frame in meta["frames"]:  # ScanNet++ writes bare file names
        frame["file_path"] = frame["file_path"].split("/")[-1]
    (dslr / "nerfstudio" / "transforms_undistorted.json").write_text(json.dumps(meta))
    (tmp_path / "scans").mkdir()
    (tmp_path / "scans" / "mesh_aligned_0.05.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    scene = load_scene(tmp_path)
    assert scene.layout == "scannetpp" and len(scene.cameras) == 2
    assert scene.surface_mesh.name == "mesh_aligned_0.05.ply"


def test_masks_and_candidates(colmap_scene):
    masks = colmap_scene / "masks"
    masks.mkdir()
    cv2.imwrite(str(masks / "0000.png"), np.zeros((HEIGHT, WIDTH), np.uint16))
    cand = colmap_scene / "candidates" / "3"
    cand.mkdir(parents=True)
    (cand / "mug.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    write_splat(cand / "mug_gaussians.ply", n=5)
    (cand / "other.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    scene = load_scene(colmap_scene)
    assert scene.masks[0].name == "0000.png" and scene.masks[1:] == (None, None)
    by_name = {c.name: c for c in scene.candidates[3]}
    assert by_name["mug"].gaussians.name == "mug_gaussians.ply"
    assert by_name["other"].gaussians is None


# --- bad input: file, field, expectation; the CLI prints one line and exits non-zero ---


def run_cli(capsys, *args) -> tuple[int, str, str]:
    code = main(["info", *map(str, args)])
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(capsys, args, *fragments):
    code, _, err = run_cli(capsys, *args)
    assert code == 2
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for fragment in fragments:
        assert fragment in err, err


def test_missing_image_file(colmap_scene, capsys):
    (colmap_scene / "images" / "0001.png").unlink()
    assert_one_line_error(capsys, [colmap_scene], "0001.png", "image file missing", "images.txt")


def test_image_size_differs_from_camera(colmap_scene, capsys):
    write_images(colmap_scene / "images", make_cameras()[:1], size=(WIDTH * 2, HEIGHT))
    assert_one_line_error(capsys, [colmap_scene], "0000.png", "64×24", "expected 32×24")


def test_mask_size_differs_from_camera(colmap_scene, capsys):
    (colmap_scene / "masks").mkdir()
    cv2.imwrite(str(colmap_scene / "masks" / "0002.png"), np.zeros((5, 5), np.uint16))
    assert_one_line_error(capsys, [colmap_scene], "masks/0002.png", "mask size", "expected 32×24")


def test_unsupported_camera_model(tmp_path, capsys):
    write_colmap_text(tmp_path / "sparse" / "0", make_cameras())
    cams_txt = tmp_path / "sparse" / "0" / "cameras.txt"
    pinhole = "PINHOLE 32 24 30.0 30.0 16.0 12.0"
    assert pinhole in cams_txt.read_text()
    cams_txt.write_text(cams_txt.read_text().replace(pinhole, "FOV 32 24 30 30 16 12 0.1"))
    write_images(tmp_path / "images", make_cameras())
    assert_one_line_error(capsys, [tmp_path], "cameras.txt", "FOV")


def test_truncated_and_malformed_gaussians(colmap_scene, capsys):
    ply = colmap_scene / "point_cloud" / "iteration_30000" / "point_cloud.ply"
    raw = ply.read_bytes()
    ply.write_bytes(raw[:-7])
    assert_one_line_error(capsys, [colmap_scene], "point_cloud.ply", "truncated")
    ply.write_bytes(raw.replace(b"property float opacity", b"property float opacityX"))
    assert_one_line_error(capsys, [colmap_scene], "point_cloud.ply", "'opacity'", "missing")
    ply.write_bytes(raw + b"\0" * 4)
    assert_one_line_error(capsys, [colmap_scene], "point_cloud.ply", "trailing data beyond the declared count")
    ply.write_bytes(raw.replace(b"element vertex 100", b"element vertex 0")[: raw.index(b"end_header\n") + 11])
    assert_one_line_error(capsys, [colmap_scene], "point_cloud.ply", "no Gaussians")


def write_degenerate_splat(path, n=100) -> None:
    """``write_splat``'s Gaussians with vertex 5's y NaN, 7's quaternion zero, 9's scale e^40."""
    write_splat(path, n=n)
    raw = path.read_bytes()
    start = raw.index(b"end_header\n") + 11
    values = np.frombuffer(raw[start:], np.float32).copy().reshape(n, -1)
    names = [line.split()[-1].decode() for line in raw[:start].split(b"\n") if line.startswith(b"property")]
    values[5, names.index("y")] = np.nan
    values[7, [names.index(f"rot_{i}") for i in range(4)]] = 0.0
    values[9, names.index("scale_1")] = 40.0
    path.write_bytes(raw[:start] + values.tobytes())


def test_degenerate_gaussians_are_dropped_with_one_warning(colmap_scene, capsys):
    ply = colmap_scene / "point_cloud" / "iteration_30000" / "point_cloud.ply"
    write_degenerate_splat(ply)
    scene = load_scene(colmap_scene)
    assert scene.gaussians.num == 97 and np.isfinite(scene.gaussians.means).all()
    err = capsys.readouterr().err
    assert err == (f"phirie: warning: {ply}: dropped 3 degenerate Gaussians "
                   "(1 non-finite mean, 1 zero quaternion, 1 |log-scale| > 20)\n")
    code, out, err = run_cli(capsys, ply, "--json")  # a PLY on its own: the same
    gaussians = json.loads(out)["gaussians"]
    assert code == 0 and err.count("\n") == 1 and "dropped 3 degenerate Gaussians" in err
    assert gaussians["count"] == 97
    assert gaussians["degenerate"] == {"total": 3, "non-finite mean": 1, "zero quaternion": 1,
                                       "|log-scale| > 20": 1}


def test_all_gaussians_degenerate_is_an_error(tmp_path, capsys):
    write_splat(tmp_path / "point_cloud.ply", n=3)
    raw = (tmp_path / "point_cloud.ply").read_bytes()
    start = raw.index(b"end_header\n") + 11
    values = np.frombuffer(raw[start:], np.float32).copy().reshape(3, -1)
    values[:, -4:] = 0.0  # rot_0..3 come last in the default layout
    (tmp_path / "point_cloud.ply").write_bytes(raw[:start] + values.tobytes())
    with pytest.raises(SceneInputError, match=r"point_cloud\.ply: element vertex: all 3 Gaussians are "
                                              r"degenerate \(3 zero quaternion\)"):
        load_scene(tmp_path)
    assert_one_line_error(capsys, [tmp_path], "point_cloud.ply", "all 3 Gaussians are degenerate")


def test_missing_scene_and_bad_candidate_folder(tmp_path, capsys):
    assert_one_line_error(capsys, [tmp_path / "nope"], "does not exist")
    write_splat(tmp_path / "point_cloud.ply")
    (tmp_path / "candidates" / "mug").mkdir(parents=True)
    assert_one_line_error(capsys, [tmp_path], "candidates/mug", "integer instance id")


# --- phirie info works on each layout ---------------------------------------------------


def test_info_on_colmap_and_nerfstudio(colmap_scene, nerfstudio_scene, capsys):
    for folder, layout, count in ((colmap_scene, "colmap", 100), (nerfstudio_scene, "nerfstudio", 50)):
        code, out, _ = run_cli(capsys, folder, "--json")
        facts = json.loads(out)
        assert code == 0 and facts["layout"] == layout
        assert facts["gaussians"]["count"] == count and facts["gaussians"]["sh_degree"] == 3
        assert facts["gaussians"]["degenerate"] == {"total": 0}
        assert facts["cameras"]["models"] == {"PINHOLE": facts["cameras"]["count"]}
        assert facts["cameras"]["image_sizes"] == {f"{WIDTH}x{HEIGHT}": facts["cameras"]["count"]}
        lo, hi = np.array(facts["bounds"])
        assert np.all(lo >= -0.5) and np.all(hi <= 0.5) and np.all(hi > lo)


def test_info_console_script_on_real_donut():
    path = shared_data("gaussians", "donut_fused.ply")
    done = subprocess.run([sys.executable, "-m", "phirie_jax.cli", "info", str(path), "--json"],
                          capture_output=True, text=True, check=True)
    facts = json.loads(done.stdout)
    assert facts["gaussians"]["count"] == 45_624 and facts["gaussians"]["sh_degree"] == 0
    assert facts["cameras"] is None
    # the donut is ~21 cm across
    extent = np.subtract(*facts["bounds"][::-1])
    assert 0.15 < extent.max() < 0.3
