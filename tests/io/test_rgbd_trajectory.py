"""Redwood trajectory logs and Open3D PrimeSense intrinsics, on the real RGB-D frames."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from phirie_jax.errors import SceneInputError
from phirie_jax.io.rgbd import read_primesense_intrinsics, read_rgbd_cameras, read_trajectory_log

RGBD = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "rgbd"
needs_rgbd = pytest.mark.skipif(not (RGBD / "trajectory.log").exists(), reason="shared RGB-D data absent")
# Hand-held capture: consecutive camera centres measured 2.33, 2.42, 2.49 and 2.56 cm apart.
STEP_RANGE_M = (0.01, 0.05)
ROTATION_TOL = 1e-9


@needs_rgbd
def test_real_trajectory_is_rigid():
    poses = read_trajectory_log(RGBD / "trajectory.log")
    assert len(poses) == 5
    for pose in poses:
        assert pose.shape == (4, 4) and pose.dtype == np.float64
        rot = pose[:3, :3]
        np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=ROTATION_TOL)
        assert np.linalg.det(rot) == pytest.approx(1.0, abs=ROTATION_TOL)
        np.testing.assert_array_equal(pose[3], [0, 0, 0, 1])
    steps = np.linalg.norm(np.diff([p[:3, 3] for p in poses], axis=0), axis=1)
    assert np.all((steps > STEP_RANGE_M[0]) & (steps < STEP_RANGE_M[1])), steps


@needs_rgbd
def test_primesense_intrinsics_pixel_centres():
    intrinsics = read_primesense_intrinsics(RGBD / "camera_primesense.json")
    assert (intrinsics.width, intrinsics.height) == (640, 480)
    # Open3D's (319.5, 239.5) counts pixel centres at integers; ours at +0.5.
    np.testing.assert_array_equal(intrinsics.K, [[525.0, 0, 320.0], [0, 525.0, 240.0], [0, 0, 1]])


@needs_rgbd
def test_real_rgbd_cameras():
    cameras = read_rgbd_cameras(RGBD / "camera_primesense.json", RGBD / "trajectory.log", RGBD / "color")
    assert [c.name for c in cameras] == [f"{i:05d}.jpg" for i in range(5)]
    for camera, pose in zip(cameras, read_trajectory_log(RGBD / "trajectory.log")):
        np.testing.assert_allclose(camera.world_to_camera @ pose, np.eye(4), atol=1e-12)
        assert camera.image_path == (RGBD / "color" / camera.name).absolute()
        assert (camera.width, camera.height, camera.model) == (640, 480, "PINHOLE")
    # The frames look at the same scene: a point 1.5 m ahead of the first camera stays in view.
    target = cameras[0].camera_to_world @ np.array([0.0, 0.0, 1.5, 1.0])
    for camera in cameras:
        uv, depth = camera.project(target[None, :3])
        assert depth[0] > 0 and 0 <= uv[0, 0] < 640 and 0 <= uv[0, 1] < 480


def _log(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    "text, expected",
    [
        ("0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0\n", "4 non-empty lines (expected 5 per frame"),
        ("0 0\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "frame 0 (line 1): header '0 0' (expected 3 integers)"),
        ("0 0 1\n1 0 0 0\n0 1 x 0\n0 0 1 0\n0 0 0 1\n", "line 3: '0 1 x 0' (expected 4 numbers)"),
        ("0 0 1\n2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "rotation part is not a rotation"),
    ],
)
def test_bad_logs(tmp_path, text, expected):
    path = _log(tmp_path / "bad.log", text)
    with pytest.raises(SceneInputError) as err:
        read_trajectory_log(path)
    assert str(err.value).startswith(str(path)) and expected in str(err.value)


def test_log_with_blank_lines_and_rounded_rows(tmp_path):
    c, s = np.cos(0.3), np.sin(0.3)
    text = (f"0 0 1\n{c:.6f} {-s:.6f} 0 1\n{s:.6f} {c:.6f} 0 2\n0 0 1 3\n0 0 0 1\n\n"
            "1 1 2\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    poses = read_trajectory_log(_log(tmp_path / "t.log", text))
    assert len(poses) == 2
    np.testing.assert_array_equal(poses[0][:3, 3], [1, 2, 3])


def test_pose_count_must_match_images(tmp_path):
    (tmp_path / "color").mkdir()
    (tmp_path / "color" / "00000.jpg").write_bytes(b"")
    _log(tmp_path / "t.log", "0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n" * 2)
    intrinsics = '{"width": 4, "height": 3, "intrinsic_matrix": [2, 0, 0, 0, 2, 0, 1.5, 1, 1]}'
    (tmp_path / "k.json").write_text(intrinsics)
    with pytest.raises(SceneInputError, match="2 poses for 1 colour images"):
        read_rgbd_cameras(tmp_path / "k.json", tmp_path / "t.log", tmp_path / "color")
    (tmp_path / "k.json").write_text('{"width": 4, "height": 3, "intrinsic_matrix": [2, 0, 0]}')
    with pytest.raises(SceneInputError, match="k.json: intrinsic_matrix: expected 9 numbers"):
        read_primesense_intrinsics(tmp_path / "k.json")
