"""Structure from motion on photos with known cameras: it recovers them, and says when it cannot."""

from __future__ import annotations

import numpy as np
import pytest

from phirie_jax.capture.config import FramesConfig, SfmConfig
from phirie_jax.capture.frames import prepare_frames
from phirie_jax.errors import SceneInputError

pytest.importorskip("pycolmap")

# Sixteen 320 px photos on the 110° arc (7° apart): centres 0.24-0.41 % of the scene size from the truth
# over threads 1-2 and seeds 0-1, rotations 0.49-0.70°, the focal length 2-3 % long. Twelve photos
# (10° apart) pinned the arc's end cameras only to 0.6-1.1 % (1.13 % on another CPU).
CENTRE_TOL = 0.01   # of the scene size (the largest distance between two true camera centres)
ROTATION_TOL = 1.0  # degrees
FOCAL_TOL = 0.05    # relative
ACCURACY_PHOTOS = 16


def sim3_residuals(estimated, truth) -> tuple[np.ndarray, np.ndarray]:
    """Camera centre errors (V,) and rotation errors (V,) in degrees after the Sim(3) that best maps
    the estimated frame onto the true one: its rotation the chordal mean of the cameras' relative
    rotations, its scale and translation least squares on the centres."""
    r_est = np.array([c.world_to_camera[:3, :3] for c in estimated])
    r_true = np.array([c.world_to_camera[:3, :3] for c in truth])
    u, _, vt = np.linalg.svd(np.einsum("vji,vjk->ik", r_est, r_true))
    rot = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt   # true world → estimated world
    est = np.array([c.center for c in estimated]) @ rot          # estimated centres, true axes
    true = np.array([c.center for c in truth])
    a, b = est - est.mean(0), true - true.mean(0)
    scale = np.sum(a * b) / np.sum(a * a)
    centre_error = np.linalg.norm(scale * a - b, axis=1)
    relative = np.einsum("vij,jk,vlk->vil", r_est, rot, r_true)  # R_est · rot · R_trueᵀ, identity if right
    angle = np.degrees(np.arccos(np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return centre_error, angle


@pytest.fixture(scope="module")
def dense_arc_photos(tmp_path_factory):
    from tests.capture.photos import render_photos

    folder = tmp_path_factory.mktemp("dense_arc") / "photos"
    folder.mkdir()
    return folder, render_photos(folder, count=ACCURACY_PHOTOS)


def test_sfm_recovers_the_cameras_of_rendered_photos(dense_arc_photos, tmp_path):
    from phirie_jax.capture.sfm import run_sfm

    folder, truth = dense_arc_photos
    frames = prepare_frames(folder, FramesConfig(), tmp_path / "frames")
    result = run_sfm(frames, SfmConfig(threads=2), tmp_path / "sfm")
    assert result.record["registered"] == len(truth), result.record
    assert result.record["mean_reprojection_error_px"] < 1.0
    by_name = {c.name: c for c in truth}
    assert all(c.model == "PINHOLE" and c.image_path.is_file() for c in result.cameras)
    centres, angles = sim3_residuals(result.cameras, [by_name[c.name] for c in result.cameras])
    size = max(np.linalg.norm(a.center - b.center) for a in truth for b in truth)
    assert centres.max() < CENTRE_TOL * size, centres / size
    assert angles.max() < ROTATION_TOL, angles
    focal = truth[0].K[0, 0]
    assert all(abs(c.K[0, 0] / focal - 1) < FOCAL_TOL for c in result.cameras), [c.K[0, 0] for c in result.cameras]
    assert len(result.points) > 100 and result.colours.dtype == np.uint8


def test_colmap_defaults_register_few_of_the_same_photos(arc_photos, tmp_path):
    """Why ``SfmConfig`` is looser than COLMAP: with COLMAP's thresholds the same orbit fails."""
    import dataclasses

    from phirie_jax.capture.config import COLMAP_DEFAULTS
    from phirie_jax.capture.sfm import run_sfm

    folder, _ = arc_photos
    frames = prepare_frames(folder, FramesConfig(), tmp_path / "frames")
    with pytest.raises(SceneInputError, match=r"[0-6] of 12 pictures registered"):
        run_sfm(frames, dataclasses.replace(SfmConfig(threads=2), **COLMAP_DEFAULTS), tmp_path / "sfm")


def test_pictures_that_do_not_register_are_one_error_with_advice(tmp_path):
    import cv2

    from phirie_jax.capture.sfm import run_sfm

    rng = np.random.default_rng(0)
    folder = tmp_path / "noise"
    folder.mkdir()
    for i in range(6):  # unrelated random textures: features everywhere, no geometry between them
        cv2.imwrite(str(folder / f"{i}.png"), cv2.GaussianBlur(rng.integers(0, 255, (120, 160, 3), np.uint8), (3, 3), 0))
    frames = prepare_frames(folder, FramesConfig(), tmp_path / "frames")
    with pytest.raises(SceneInputError, match=r"of 6 pictures registered .* expected at least 60 %\): try more photos"):
        run_sfm(frames, SfmConfig(threads=2), tmp_path / "sfm")


def test_sim3_residuals_of_a_moved_copy_are_zero():
    """The check itself: a scaled, rotated, shifted copy of the cameras has no residual."""
    from scipy.spatial.transform import Rotation

    from tests.capture.photos import arc_cameras

    truth = arc_cameras(5, 64, 48)
    rot = Rotation.from_euler("xyz", [20, -35, 70], degrees=True).as_matrix()
    moved = []
    for c in truth:  # world' = 2.5 rot x + t: world_to_camera' = [R rotᵀ | 2.5 t_c − R rotᵀ t]
        w2c = np.eye(4)
        w2c[:3, :3] = c.world_to_camera[:3, :3] @ rot.T
        w2c[:3, 3] = 2.5 * c.world_to_camera[:3, 3] - w2c[:3, :3] @ np.array([0.3, -1.0, 2.0])
        moved.append(type(c)(c.name, c.K, w2c, c.width, c.height))
    centres, angles = sim3_residuals(moved, truth)
    assert centres.max() < 1e-9 and angles.max() < 1e-5
