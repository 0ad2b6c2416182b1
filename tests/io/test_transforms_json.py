"""transforms.json: OpenGL ↔ OpenCV conventions, intrinsics layouts, dataset variants."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from phirie_jax.errors import SceneInputError
from phirie_jax.io.camera import intrinsics_matrix, outside_paths_allowed
from phirie_jax.io.colmap import read_colmap_model
from phirie_jax.io.transforms_json import read_transforms_json, write_transforms_json
from phirie_jax.types import Camera

POSE_TOL = 1e-12
IDENTITY_AT_Z5 = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]]


def write_json(path: Path, meta: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(meta))
    return path


def write_image(path: Path, width: int, height: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.zeros((height, width, 3), np.uint8))


def random_camera(rng: np.random.Generator, name: str, model: str = "PINHOLE", distortion=()) -> Camera:
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    rot = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = rot, rng.normal(size=3) * 3
    fx = rng.uniform(300, 900)
    fy = fx if model == "SIMPLE_PINHOLE" else rng.uniform(300, 900)
    return Camera(name, intrinsics_matrix(fx, fy, *rng.uniform(100, 300, size=2)), w2c, 640, 480, model,
                  np.asarray(distortion, dtype=np.float64))


def assert_same(read: list[Camera], written: list[Camera]) -> None:
    assert [c.name for c in read] == sorted(c.name for c in written)
    by_name = {c.name: c for c in written}
    for camera in read:
        expected = by_name[camera.name]
        np.testing.assert_array_equal(camera.K, expected.K)
        np.testing.assert_allclose(camera.world_to_camera, expected.world_to_camera, rtol=0, atol=POSE_TOL)
        assert (camera.width, camera.height, camera.model) == (expected.width, expected.height, expected.model)
        np.testing.assert_array_equal(camera.distortion, expected.distortion)


# --- conventions ---------------------------------------------------------------------------


def test_camera_at_z5_looking_at_origin_matches_colmap(tmp_path):
    """OpenGL c2w identity rotation at (0, 0, 5) looks down −z with +y up: the origin is
    at the principal point, 5 in front; the COLMAP reader gives the same camera for
    qvec (0, 1, 0, 0), t (0, 0, 5) (see test_colmap)."""
    path = write_json(tmp_path / "transforms.json", {
        "fl_x": 500, "fl_y": 500, "cx": 320, "cy": 240, "w": 640, "h": 480,
        "frames": [{"file_path": "images/cam.png", "transform_matrix": IDENTITY_AT_Z5}],
    })
    (camera,) = read_transforms_json(path)
    uv, depth = camera.project(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]))
    np.testing.assert_allclose(uv[0], [320, 240])
    assert depth[0] == pytest.approx(5.0)
    assert uv[1, 0] > 320 and uv[2, 1] < 240  # world +x is image right, world +y is image up

    sparse = tmp_path / "sparse"
    sparse.mkdir()
    (sparse / "cameras.txt").write_text("1 PINHOLE 640 480 500 500 320 240\n")
    (sparse / "images.txt").write_text("1 0 1 0 0 0 0 5 1 cam.png\n\n")
    (colmap,), _ = read_colmap_model(sparse)
    assert colmap.name == camera.name
    np.testing.assert_allclose(camera.world_to_camera, colmap.world_to_camera, atol=1e-15)
    np.testing.assert_array_equal(camera.K, colmap.K)


def test_opengl_matrix_in_file(tmp_path):
    """The written matrix is the OpenGL camera-to-world: its −z column is the viewing direction."""
    camera = random_camera(np.random.default_rng(0), "a.png")
    write_transforms_json(tmp_path / "transforms.json", [camera])
    (frame,) = json.loads((tmp_path / "transforms.json").read_text())["frames"]
    c2w = np.asarray(frame["transform_matrix"])
    np.testing.assert_allclose(c2w[:3, 3], camera.center, atol=1e-12)
    np.testing.assert_allclose(-c2w[:3, 2], camera.world_to_camera[2, :3], atol=1e-12)   # forward
    np.testing.assert_allclose(-c2w[:3, 1], camera.world_to_camera[1, :3], atol=1e-12)   # down


# --- round trips ---------------------------------------------------------------------------


def test_round_trip_shared_intrinsics(tmp_path):
    rng = np.random.default_rng(1)
    first = random_camera(rng, "frame_00002.png", "OPENCV", [0.1, -0.02, 0.001, -0.003, 0.0004])
    cameras = [first] + [
        dataclasses.replace(random_camera(rng, f"frame_{i:05d}.png"), K=first.K, model="OPENCV",
                            distortion=first.distortion)
        for i in (0, 1, 3)
    ]
    path = tmp_path / "transforms.json"
    write_transforms_json(path, cameras)
    meta = json.loads(path.read_text())
    assert meta["camera_model"] == "OPENCV" and meta["k3"] == 0.0004
    assert all(set(frame) == {"file_path", "transform_matrix"} for frame in meta["frames"])
    assert meta["frames"][0]["file_path"] == "images/frame_00000.png"
    read = read_transforms_json(path)
    assert_same(read, cameras)
    assert read[0].image_path == (tmp_path / "images" / "frame_00000.png")


def test_round_trip_per_frame_intrinsics(tmp_path):
    rng = np.random.default_rng(2)
    cameras = [
        random_camera(rng, "b.png"),
        random_camera(rng, "a.png", "SIMPLE_PINHOLE"),
        random_camera(rng, "sub/c.jpg", "OPENCV", [0.05, 0.0, 0.0, 0.0]),
        random_camera(rng, "d.png", "OPENCV", [0.0, 0.0, 0.0, 0.0]),
    ]
    path = tmp_path / "out" / "transforms.json"
    write_transforms_json(path, cameras, image_dir_name="rgb")
    meta = json.loads(path.read_text())
    assert "fl_x" not in meta and all("fl_x" in frame for frame in meta["frames"])
    assert [f["camera_model"] for f in meta["frames"]] == ["SIMPLE_PINHOLE", "PINHOLE", "OPENCV", "OPENCV"]
    assert_same(read_transforms_json(path), cameras)
    assert sorted(p.name for p in path.parent.iterdir()) == ["transforms.json"]  # no temporary left


# --- intrinsics layouts --------------------------------------------------------------------


def test_per_frame_overrides_top_level(tmp_path):
    path = write_json(tmp_path / "transforms.json", {
        "fl_x": 500, "fl_y": 510, "cx": 320, "cy": 240, "w": 640, "h": 480, "k1": 0.1,
        "frames": [
            {"file_path": "a.png", "transform_matrix": IDENTITY_AT_Z5},
            {"file_path": "b.png", "transform_matrix": IDENTITY_AT_Z5, "fl_x": 600, "w": 800, "k1": 0.0,
             "camera_model": "PINHOLE"},
            {"file_path": "c.png", "transform_matrix": IDENTITY_AT_Z5, "camera_angle_x": math.pi / 2},
        ],
    })
    a, b, c = read_transforms_json(path)
    np.testing.assert_array_equal(a.K, intrinsics_matrix(500, 510, 320, 240))
    assert (a.model, a.width, list(a.distortion)) == ("OPENCV", 640, [0.1, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(b.K, intrinsics_matrix(600, 510, 320, 240))
    assert (b.model, b.width, b.distortion.size) == ("PINHOLE", 800, 0)
    assert c.K[0, 0] == pytest.approx(320.0)  # the frame's angle beats the top-level fl_x


def test_camera_angle_x_blender(tmp_path):
    """Blender / instant-ngp: only a horizontal field of view; principal point at the centre."""
    angle = 0.6911112070083618  # NeRF-synthetic lego
    path = write_json(tmp_path / "transforms_train.json", {
        "camera_angle_x": angle, "w": 800, "h": 800,
        "frames": [{"file_path": "./train/r_0", "rotation": 0.0126, "transform_matrix": IDENTITY_AT_Z5}],
    })
    (camera,) = read_transforms_json(path)
    focal = 0.5 * 800 / math.tan(0.5 * angle)
    assert focal == pytest.approx(1111.1110311937682)
    np.testing.assert_allclose(camera.K, intrinsics_matrix(focal, focal, 400, 400), rtol=1e-15)
    assert camera.model == "PINHOLE"


def test_blender_path_without_extension(tmp_path):
    write_image(tmp_path / "train" / "r_0.png", 20, 10)
    write_image(tmp_path / "train" / "r_1.jpg", 20, 10)
    path = write_json(tmp_path / "transforms_train.json", {
        "camera_angle_x": 0.69,
        "frames": [{"file_path": "./train/r_1", "transform_matrix": IDENTITY_AT_Z5},
                   {"file_path": "./train/r_0", "transform_matrix": IDENTITY_AT_Z5}],
    })
    r0, r1 = read_transforms_json(path)
    assert (r0.name, r1.name) == ("r_0.png", "r_1.jpg")
    assert r0.image_path == tmp_path / "train" / "r_0.png" and r0.image_path.is_absolute()
    assert (r0.width, r0.height) == (20, 10)  # no w / h in the file: read from the image header


def test_missing_size_without_image(tmp_path):
    path = write_json(tmp_path / "transforms.json", {
        "fl_x": 500, "h": 480, "frames": [{"file_path": "images/a.png", "transform_matrix": IDENTITY_AT_Z5}],
    })
    with pytest.raises(SceneInputError) as err:
        read_transforms_json(path)
    assert str(err.value).startswith(f"{path}: w: missing")


def test_missing_focal(tmp_path):
    path = write_json(tmp_path / "transforms.json", {
        "w": 10, "h": 10, "frames": [{"file_path": "a.png", "transform_matrix": IDENTITY_AT_Z5}],
    })
    with pytest.raises(SceneInputError, match=r"frames\[0\]: fl_x: missing"):
        read_transforms_json(path)


def test_scannetpp_layout(tmp_path):
    """Bare file names resolved against image_root; is_bad frames; test_frames included."""
    images = tmp_path / "dslr" / "undistorted_images"
    meta = {
        "camera_model": "PINHOLE", "fl_x": 700.5, "fl_y": 701.5, "cx": 876.0, "cy": 584.0, "w": 1752, "h": 1168,
        "frames": [
            {"file_path": "DSC00002.JPG", "transform_matrix": IDENTITY_AT_Z5, "is_bad": False,
             "mask_path": "DSC00002.png"},
            {"file_path": "DSC00001.JPG", "transform_matrix": IDENTITY_AT_Z5, "is_bad": True},
        ],
        "test_frames": [{"file_path": "DSC00003.JPG", "transform_matrix": IDENTITY_AT_Z5, "is_bad": False}],
    }
    path = write_json(tmp_path / "dslr" / "nerfstudio" / "transforms_undistorted.json", meta)
    cameras = read_transforms_json(path, image_root=images)
    assert [c.name for c in cameras] == ["DSC00001.JPG", "DSC00002.JPG", "DSC00003.JPG"]
    assert cameras[0].image_path == images.absolute() / "DSC00001.JPG"
    assert [c.name for c in read_transforms_json(path, images, skip_bad=True)] == ["DSC00002.JPG", "DSC00003.JPG"]

    meta["camera_model"] = "OPENCV_FISHEYE"  # ScanNet++'s raw DSLR transforms.json
    write_json(path, meta)
    with pytest.raises(SceneInputError) as err:
        read_transforms_json(path, images)
    assert str(err.value).startswith(f"{path}: camera_model: unsupported camera model OPENCV_FISHEYE")


@pytest.mark.parametrize(
    "extra, expected",
    [
        ({"camera_model": "EQUIRECTANGULAR"}, "camera_model: unsupported camera model EQUIRECTANGULAR"),
        ({"is_fisheye": True}, "unsupported camera model fisheye"),
        ({"camera_model": "PINHOLE", "k1": 0.1}, "PINHOLE with nonzero distortion"),
        ({"k4": 0.1}, "k4: 0.1 (OPENCV has no k4"),
        ({"w": 640.5}, "w: 640.5 (expected a positive whole number"),
        ({"fl_x": "500"}, "fl_x: '500' (expected a finite number)"),
        ({"camera_angle_x": 4.0, "fl_x": None}, "camera_angle_x: 4.0 (expected a field of view"),
    ],
)
def test_bad_intrinsics(tmp_path, extra, expected):
    meta = {"fl_x": 500, "w": 640, "h": 480, **extra,
            "frames": [{"file_path": "a.png", "transform_matrix": IDENTITY_AT_Z5}]}
    meta = {k: v for k, v in meta.items() if v is not None}
    path = write_json(tmp_path / "transforms.json", meta)
    with pytest.raises(SceneInputError) as err:
        read_transforms_json(path)
    assert expected in str(err.value)


def test_opencv_distortion_order(tmp_path):
    path = write_json(tmp_path / "transforms.json", {
        "camera_model": "OPENCV", "fl_x": 500, "w": 640, "h": 480,
        "k1": 0.1, "k2": 0.2, "k3": 0.3, "p1": 0.01, "p2": 0.02,
        "frames": [{"file_path": "a.png", "transform_matrix": IDENTITY_AT_Z5}],
    })
    (camera,) = read_transforms_json(path)
    np.testing.assert_array_equal(camera.distortion, [0.1, 0.2, 0.01, 0.02, 0.3])  # OpenCV k1 k2 p1 p2 k3


# --- poses ---------------------------------------------------------------------------------


def test_rounded_pose_is_snapped_to_a_rotation(tmp_path):
    camera = random_camera(np.random.default_rng(3), "a.png")
    c2w = camera.camera_to_world @ np.diag([1.0, -1.0, -1.0, 1.0])
    path = write_json(tmp_path / "transforms.json", {
        "fl_x": 500, "w": 640, "h": 480,
        "frames": [{"file_path": "a.png", "transform_matrix": np.round(c2w, 6).tolist()}],
    })
    (read,) = read_transforms_json(path)
    rot = read.world_to_camera[:3, :3]
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(read.world_to_camera, camera.world_to_camera, atol=1e-5)


@pytest.mark.parametrize(
    "matrix, expected",
    [
        (np.diag([2.0, 2.0, 2.0, 1.0]).tolist(), "rotation part is not a rotation"),
        (np.diag([1.0, 1.0, -1.0, 1.0]).tolist(), "rotation part is not a rotation"),
        ([[1, 0, 0], [0, 1, 0]], "expected a 4x4 (or 3x4) matrix, got shape (2, 3)"),
        ([[1, 0, 0, 0], [0, 1, 0, float("nan")], [0, 0, 1, 0], [0, 0, 0, 1]],
         "non-finite value nan at row 1, column 3 (1 in all; expected finite numbers)"),
        ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]], "last row"),
        (None, "transform_matrix: missing"),
        ([[1, 0, "x", 0]], "expected a 4x4 matrix of numbers"),
    ],
)
def test_bad_transform_matrix(tmp_path, matrix, expected):
    frame = {"file_path": "a.png"} if matrix is None else {"file_path": "a.png", "transform_matrix": matrix}
    path = write_json(tmp_path / "transforms.json", {"fl_x": 500, "w": 640, "h": 480, "frames": [frame]})
    with pytest.raises(SceneInputError) as err:
        read_transforms_json(path)
    assert "frames[0]: transform_matrix" in str(err.value) and expected in str(err.value)


def test_bad_files(tmp_path):
    with pytest.raises(SceneInputError, match="file not found"):
        read_transforms_json(tmp_path / "missing.json")
    path = tmp_path / "transforms.json"
    path.write_text("{not json")
    with pytest.raises(SceneInputError, match="not valid JSON"):
        read_transforms_json(path)
    write_json(path, {"fl_x": 1})
    with pytest.raises(SceneInputError, match="frames: missing"):
        read_transforms_json(path)
    write_json(path, {"fl_x": 500, "w": 6, "h": 4, "frames": [
        {"file_path": "images/a.png", "transform_matrix": IDENTITY_AT_Z5},
        {"file_path": "./images/a.png", "transform_matrix": IDENTITY_AT_Z5}]})
    with pytest.raises(SceneInputError, match="'a.png' appears in more than one frame"):
        read_transforms_json(path)


# --- paths outside the folder --------------------------------------------------------------


@pytest.mark.parametrize("file_path", ["../outside/a.png", "images/../../outside/a.png", "/ABS/outside/a.png"])
def test_an_image_outside_the_folder_is_refused_before_it_is_read(tmp_path, file_path):
    """A frame may not send the reader to ``../../../etc/hostname`` or an absolute path: one line
    naming the file and frame; the image is never opened (no w/h here, so reading it would be
    the next step). ``outside_paths_allowed`` reads it."""
    outside = tmp_path / "outside" / "a.png"
    write_image(outside, 8, 6)
    file_path = file_path.replace("/ABS", str(tmp_path))
    path = write_json(tmp_path / "scene" / "transforms.json",
                      {"fl_x": 10, "frames": [{"file_path": file_path, "transform_matrix": IDENTITY_AT_Z5}]})
    with pytest.raises(SceneInputError) as err:
        read_transforms_json(path)
    assert str(err.value) == (f"{path}: frames[0]: file_path: {file_path!r} is outside {path.parent} (expected an "
                              "image inside the scene folder; --allow-outside-paths reads it anyway)")
    with outside_paths_allowed():
        (camera,) = read_transforms_json(path)
    assert camera.image_path == outside and (camera.width, camera.height) == (8, 6)
    with pytest.raises(SceneInputError, match="is outside"):  # only inside the block
        read_transforms_json(path)


def test_dot_dot_that_stays_inside_the_folder_is_fine(tmp_path):
    path = write_json(tmp_path / "transforms.json", {"fl_x": 10, "w": 8, "h": 6, "frames": [
        {"file_path": "images/../frames/a.png", "transform_matrix": IDENTITY_AT_Z5}]})
    assert read_transforms_json(path)[0].image_path == tmp_path / "frames" / "a.png"


@pytest.mark.parametrize("meta, field", [
    ({"fl_x": 0, "w": 640, "h": 480}, "transforms.json: fl_x: 0.0 (expected a positive focal length"),
    ({"fl_x": 500, "fl_y": -1, "w": 640, "h": 480}, "transforms.json: fl_y: -1.0 (expected"),
    ({"w": 640, "h": 480}, "transforms.json: frames[0]: fl_x: 0.0 (expected"),
], ids=["top-level-fl_x", "top-level-fl_y", "frame-fl_x"])
def test_a_bad_focal_length_is_named_where_it_is(tmp_path, meta, field):
    frame = {"file_path": "a.png", "transform_matrix": IDENTITY_AT_Z5}
    if "fl_x" not in meta:
        frame["fl_x"] = 0
    path = write_json(tmp_path / "transforms.json", {**meta, "frames": [frame]})
    with pytest.raises(SceneInputError) as err:
        read_transforms_json(path)
    assert field in str(err.value)
