"""``report.html`` of a converted folder: self-contained (every image inlined and decodable), a row per
object with what the manifest says, before ≈ after where the conversion is exact, thumbnails that
show their object, the rollout kept once given; the crop camera by its projection."""

from __future__ import annotations

import base64
import json
import re

import cv2
import numpy as np
import pytest

from phirie_jax import layout
from phirie_jax.io.camera import intrinsics_matrix
from phirie_jax.report.config import ReportConfig
from phirie_jax.report.page import write_report
from phirie_jax.report.renders import crop_camera, view_cameras
from phirie_jax.synthetic.scene import look_at
from phirie_jax.types import Camera
from tests.fixtures.box_scene import BOXES, converted_folder

CONFIG = ReportConfig(views=2, width=120, thumbnail=48, filmstrip=3)
SAME_SCENE_LEVELS = 4.0    # mean 8-bit difference of before and after where the conversion is exact
PIXEL_TOL = 1e-9


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    out = converted_folder(tmp_path_factory.mktemp("report"))
    path = write_report(out, CONFIG)
    return out, path, path.read_text(encoding="utf-8")


def images(page: str) -> list[np.ndarray]:
    found = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)
    return [cv2.imdecode(np.frombuffer(base64.b64decode(b), np.uint8), cv2.IMREAD_COLOR)[..., ::-1] for b in found]


def test_page_is_self_contained_and_its_images_decode(report):
    out, path, page = report
    assert path == out / layout.REPORT
    sources = re.findall(r'src="([^"]*)"', page)
    assert sources and all(s.startswith("data:image/png;base64,") for s in sources)
    assert "<link" not in page and "<script" not in page
    decoded = images(page)
    assert len(decoded) == 2 * CONFIG.views + len(BOXES)  # before, after, one thumbnail each
    assert all(img is not None and img.std() > 1.0 for img in decoded)  # nothing blank
    manifest = json.loads((out / layout.MANIFEST).read_text())
    assert manifest["report"] == {"path": layout.REPORT, "video": None}
    assert manifest["timings"]["report"] > 0


def test_every_object_has_its_row_and_the_background_and_timings_are_there(report):
    out, _, page = report
    manifest = json.loads((out / layout.MANIFEST).read_text())
    for entry in manifest["objects"]:
        row = page[page.index(f"<td>{entry['id']}</td>"):].split("</tr>")[0]
        assert "accepted" in row and "box" in row and "stable, drift 0.1 cm" in row
        assert f"{entry['mass']:.3g} kg" in row and "registration" in row and "settling" in row
    background = manifest["background"]
    assert f"{background['removed']} removed" in page and f"{background['filled']} filled" in page
    for stage in ("observe", "objects", "physics", "background"):
        assert f"<th>{stage}</th>" in page
    assert "scene.usda" in page or "no scene.usda" in page


def test_before_and_after_agree_where_the_conversion_is_exact(report):
    # the fixture's capture is its background plus its objects at their poses: converted = captured
    _, _, page = report
    decoded = images(page)
    for before, after in zip(decoded[0:2 * CONFIG.views:2], decoded[1:2 * CONFIG.views:2]):
        assert before.shape == after.shape
        assert np.abs(before.astype(float) - after.astype(float)).mean() < SAME_SCENE_LEVELS


def test_thumbnails_show_their_object(report):
    _, _, page = report
    thumbnails = images(page)[2 * CONFIG.views:]
    for (object_id, (_, rgb, *_)), thumb in zip(sorted(BOXES.items()), thumbnails):
        assert thumb.shape == (CONFIG.thumbnail, CONFIG.thumbnail, 3)
        centre = thumb[16:32, 16:32].reshape(-1, 3).mean(0)
        assert int(np.argmax(centre)) == int(np.argmax(rgb)), (object_id, centre)  # red box red, blue box blue


def test_a_rollout_is_linked_with_its_frames_and_kept(report, tmp_path):
    out, _, _ = report
    video = out / "media" / "rollout.mp4"
    video.parent.mkdir(exist_ok=True)
    video.write_bytes(b"\x00")
    frames = [np.full((40, 60, 3), 10 * k, np.uint8) for k in range(10)]
    page = write_report(out, CONFIG, video=video, frames=frames).read_text(encoding="utf-8")
    assert 'href="media/rollout.mp4"' in page
    assert len(images(page)) == 2 * CONFIG.views + len(BOXES) + CONFIG.filmstrip
    again = write_report(out, CONFIG).read_text(encoding="utf-8")  # a later report keeps the rollout
    assert 'href="media/rollout.mp4"' in again
    assert json.loads((out / layout.MANIFEST).read_text())["report"]["video"] == "media/rollout.mp4"


def test_view_cameras_spread_over_the_capture():
    cams = list(range(12))
    assert view_cameras(cams, 3) == [0, 6, 11] and view_cameras(cams, 1) == [0]
    assert view_cameras(cams, 40) == cams and view_cameras([], 3) == [] and view_cameras(cams, 0) == []


def test_crop_camera_maps_the_objects_square_to_the_centre_of_its_image():
    camera = Camera("a.png", intrinsics_matrix(200.0, 190.0, 81.0, 59.0),
                    look_at(np.array([0.5, -0.4, 0.4]), np.array([0.0, 0.0, 0.05])), 160, 120)
    corners = np.array([[x, y, z] for x in (-0.03, 0.04) for y in (-0.02, 0.05) for z in (0.0, 0.08)])
    crop, side = crop_camera(camera, corners, 90, 60)
    assert (crop.width, crop.height) == (90, 60)
    uv, _ = camera.project(corners)
    low, high = uv.min(0), uv.max(0)
    corner = 0.5 * (low + high) - 0.5 * side
    scale = 60 / side
    points = np.random.default_rng(0).uniform(-0.05, 0.08, (25, 3))
    expected = scale * (camera.project(points)[0] - corner) + [15.0, 0.0]  # the 60 × 60 square, centred
    assert np.allclose(crop.project(points)[0], expected, atol=PIXEL_TOL)
    projected = crop.project(corners)[0]
    assert projected.min() >= 0 and projected[:, 0].max() <= 75 and projected[:, 1].max() <= 60
    assert crop_camera(camera, corners + [5.0, 0.0, 0.0], 90, 60) is None   # out of the image
