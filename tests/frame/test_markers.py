"""Fiducial markers: photos of a printed 5 cm ArUco marker (drawn by its homography into each
camera of a tilted, non-metric capture) give the scale within 1 % and up within a degree; the
synthetic table's printed marker (``phirie synth --marker``) gives the scale with truth."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from phirie_jax.frame import estimate, markers
from phirie_jax.frame.config import FrameConfig
from phirie_jax.frame.resolve import resolve_frame, world_camera
from phirie_jax.geometry import sim3_matrix, split_sim3
from phirie_jax.synthetic.scene import look_at
from phirie_jax.types import Camera, SceneInput

SIDE = 0.05                 # metres: the black square
UNITS_PER_METRE = 3.7
TILT = Rotation.from_euler("xyz", [-40, 25, 110], degrees=True).as_matrix()
WORLD_TO_CAPTURE = sim3_matrix(UNITS_PER_METRE, TILT, np.array([0.3, 0.2, -1.1]))
SHEET_PX, MARKER_PX = 900, 600    # the printed sheet's image: marker plus a white margin


def sheet_image(dictionary: str = "DICT_4X4_50", ident: int = 7) -> np.ndarray:
    marker = cv2.aruco.generateImageMarker(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)),
                                           ident, MARKER_PX, borderBits=1)
    pad = (SHEET_PX - MARKER_PX) // 2
    return np.pad(marker, pad, constant_values=255)


def photograph(sheet: np.ndarray, K: np.ndarray, world_to_camera: np.ndarray, size=(640, 480)) -> np.ndarray:
    """The sheet (lying on z = 0, centred at the origin, its image's x along +x and y along −y)
    seen by a pinhole camera (K with pixel centres at i + 0.5), slightly blurred and noisy."""
    metres = SIDE * SHEET_PX / MARKER_PX
    to_plane = np.array([[metres / SHEET_PX, 0, metres * (0.5 / SHEET_PX - 0.5)],
                         [0, -metres / SHEET_PX, -metres * (0.5 / SHEET_PX - 0.5)], [0, 0, 1]])
    k_cv = K.copy()
    k_cv[:2, 2] -= 0.5
    h = k_cv @ world_to_camera[:3][:, [0, 1, 3]] @ to_plane
    photo = cv2.warpPerspective(sheet, h, size, flags=cv2.INTER_AREA, borderValue=140)
    photo = cv2.GaussianBlur(photo, (0, 0), 0.8).astype(np.float64)
    photo += np.random.default_rng(int(world_to_camera[0, 3] * 1e6) % 2**32).normal(0, 2.0, photo.shape)
    return np.clip(photo, 0, 255).astype(np.uint8)


def capture(tmp_path, eyes, ident: int = 7) -> tuple[Camera, ...]:
    """Cameras of the tilted capture looking at the marker from ``eyes`` (world, metres), their
    photos written to ``tmp_path``."""
    K = np.array([[520.0, 0, 320], [0, 520.0, 240], [0, 0, 1]])
    sheet = sheet_image(ident=ident)
    cameras = []
    for i, eye in enumerate(eyes):
        w2c = look_at(np.asarray(eye, float), np.array([0.01, -0.01, 0.0]))
        path = tmp_path / f"{i:02d}.png"
        cv2.imwrite(str(path), photograph(sheet, K, w2c))
        metric = Camera(path.name, K, w2c, 640, 480, image_path=path)
        cameras.append(world_camera(metric, WORLD_TO_CAPTURE))   # the same camera in the capture's frame
    return tuple(cameras)


EYES = [(0.25 * np.cos(a), 0.25 * np.sin(a), 0.3) for a in np.radians([0, 70, 150, 220, 300])]


def test_markers_give_metres_and_up(tmp_path):
    cameras = capture(tmp_path, EYES)
    found = markers.markers(cameras, markers.detect(cameras))
    assert [(m.dictionary, m.ident, len(m.views)) for m in found] == [("DICT_4X4_250", 7, 5)]
    scale, band = markers.marker_scale(found, SIDE)
    assert scale * UNITS_PER_METRE == pytest.approx(1.0, rel=0.01)
    assert 1 / band <= scale * UNITS_PER_METRE <= band < 1.03
    assert estimate.angle_deg(found[0].normal(cameras), TILT[:, 2]) < 1.0   # the truth's +z in the capture
    # the frame: metres from the markers, their plane a cue and the support
    scene = SceneInput(tmp_path, "nerfstudio", None, None, cameras)
    frame = resolve_frame(scene, FrameConfig(marker_size=SIDE, marker_dictionary="DICT_4X4_50"))
    assert frame.scale_source.startswith("markers (--marker-size 0.05): DICT_4X4_50 id 7 in 5 photos")
    assert not frame.scale_is_prior and frame.warnings == ()
    truth_scale, rotation, _ = split_sim3(frame.capture_to_world @ WORLD_TO_CAPTURE)
    assert truth_scale == pytest.approx(1.0, rel=0.01) and np.degrees(np.arccos(rotation[2, 2])) < 1.0
    assert frame.support is not None and frame.support.source == "markers"
    assert frame.record()["evidence"]["markers"][0]["views"] == 5


def test_a_marker_in_two_photos_is_weak_and_none_is_a_warning(tmp_path):
    cameras = capture(tmp_path, EYES[:2])
    scene = SceneInput(tmp_path, "nerfstudio", None, None, cameras)
    frame = resolve_frame(scene, FrameConfig(marker_size=SIDE))
    assert frame.scale_uncertainty >= markers.WEAK_BAND
    assert any(w.startswith("--marker-size 0.05: the markers are seen in at most 2 photos") for w in frame.warnings)
    (tmp_path / "blank").mkdir()
    blank = []
    for camera in cameras:
        path = tmp_path / "blank" / camera.name
        cv2.imwrite(str(path), np.full((480, 640), 140, np.uint8))
        blank.append(Camera(camera.name, camera.K, camera.world_to_camera, 640, 480, image_path=path))
    with pytest.raises(Exception, match="scale: cannot be estimated"):   # no Gaussians, no marker: nothing
        resolve_frame(SceneInput(tmp_path, "nerfstudio", None, None, tuple(blank)), FrameConfig(marker_size=SIDE))


def test_synth_prints_a_marker_the_frame_measures(tilted_tabletop):
    """``synthesize(..., marker=0.25)`` on the tiny preset (128 × 96 photos): the marker is found,
    its triangulated corners lie on the true ones, and the scale is within 2 % and its stated band
    (a square of ~20 px: its corners from its fitted edges, not the rounded corners themselves)."""
    from phirie_jax.io.scene import load_scene
    from tests.frame.conftest import MARKER_SIDE
    from tests.frame.conftest import UNITS_PER_METRE as UNITS
    from tests.frame.conftest import WORLD_TO_CAPTURE as TO_CAPTURE

    original, tilted = tilted_tabletop
    truth = json.loads((original / "gt" / "markers.json").read_text())
    assert [(t["dictionary"], t["id"], t["side"]) for t in truth] == [("DICT_4X4_50", 0, MARKER_SIDE)]
    scene = load_scene(tilted)
    found = markers.markers(scene.cameras, markers.detect(scene.cameras, "DICT_4X4_50"))
    assert len(found) == 1 and len(found[0].views) >= 3
    corners = np.asarray(truth[0]["corners"]) @ TO_CAPTURE[:3, :3].T + TO_CAPTURE[:3, 3]
    assert np.abs(found[0].corners - corners).max() < 0.03 * UNITS   # 3 cm, at 20 px a side
    frame = resolve_frame(scene, FrameConfig(marker_size=MARKER_SIDE))
    ratio = frame.scale * UNITS
    assert 1 / frame.scale_uncertainty <= ratio <= frame.scale_uncertainty and abs(ratio - 1) < 0.02, ratio


@pytest.mark.slow
def test_synth_marker_gives_the_scale_within_2_percent(tmp_path):
    """The default preset (320 × 240 photos) with a 15 cm marker: seen in ≥ 3 views, the scale is
    within 2 % of the truth and inside its band; up within half a degree."""
    from phirie_jax.io.scene import load_scene
    from phirie_jax.synthetic import synthesize
    from phirie_jax.synthetic.reframe import reframe_scene

    synthesize(tmp_path / "scene", preset="default", seed=1, marker=0.15)
    reframe_scene(tmp_path / "scene", tmp_path / "tilted", WORLD_TO_CAPTURE)
    frame = resolve_frame(load_scene(tmp_path / "tilted"), FrameConfig(marker_size=0.15))
    (marker,) = frame.evidence["markers"]
    assert marker["views"] >= 3
    scale, rotation, _ = split_sim3(frame.capture_to_world @ WORLD_TO_CAPTURE)
    assert abs(scale - 1) < 0.02 and 1 / frame.scale_uncertainty <= scale <= frame.scale_uncertainty
    assert np.degrees(np.arccos(rotation[2, 2])) < 0.5


def test_a_blurred_squares_corners_are_where_its_edges_meet():
    """A 24 px black square on white paper, blurred by 1.5 px: corner detection rounds its corners
    inwards; the fitted edges put them back within a tenth of a pixel."""
    truth = np.array([[20.3, 20.7], [44.3, 20.7], [44.3, 44.7], [20.3, 44.7]])   # OpenCV pixels (centres at integers)
    size = 8 * 65
    sheet = np.full((size, size), 230.0)
    ys, xs = np.mgrid[0:size, 0:size] / 8.0 - 0.5 + 1 / 16   # 8×8 samples per pixel, at their centres
    inside = (xs >= truth[0, 0]) & (xs < truth[1, 0]) & (ys >= truth[0, 1]) & (ys < truth[2, 1])
    sheet[inside] = 25.0
    image = cv2.GaussianBlur(sheet.reshape(65, 8, 65, 8).mean(axis=(1, 3)), (0, 0), 1.5)
    rounded = truth + np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]]) * 0.8   # where a corner detector lands
    fitted = markers.edge_corners(image, rounded, 6)
    assert np.abs(fitted - truth).max() < 0.1
    assert np.array_equal(markers.edge_corners(np.full((65, 65), 128.0), rounded, 6), rounded)   # no edge: unchanged
