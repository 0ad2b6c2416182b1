"""``phirie view`` in a real browser: the server on loopback, Debian's Chromium headless (software
WebGL) driven by Playwright. The page draws the scene (non-blank; the objects' pixels change when
"Background only" hides them), a click on an object shoots it and a drag pulls another: the server
sees them move.
Skipped, with the reason, where Chromium, Playwright or viser is missing (CI installs them)."""

from __future__ import annotations

import shutil
import socket
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from phirie_jax.view.scene import CameraView, screen_position
from tests.fixtures.box_scene import converted_folder

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
if not Path(CHROMIUM).is_file():
    pytest.skip("Chromium is not installed (Debian: apt-get install chromium; .ci/run installs it)",
                allow_module_level=True)
pytest.importorskip("viser", reason="viser is not installed (the viewer extra)")
sync_playwright = pytest.importorskip("playwright.sync_api", reason="playwright is not installed").sync_playwright

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run",
         "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]   # software WebGL, no GPU
VIEWPORT = {"width": 1000, "height": 700}
WAIT_S = 60.0            # for the page to connect, draw and answer (software WebGL on a busy CPU)
BLANK_STD = 5.0          # 8-bit levels: a drawn scene varies more than an empty canvas
OBJECT_CHANGE = 20.0     # mean 8-bit colour change where an object was, when it is hidden
MOVED_M = 0.01           # a shot or dragged object moves more than this
DRAG_PX, DRAG_STEPS = 120, 5    # the drag: pixels to the left, in pointer moves (each waits for a frame: ~1 s)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def until(condition, what: str, timeout: float = WAIT_S):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = condition()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.fixture(scope="module")
def viewer(tmp_path_factory):
    from phirie_jax.view.config import ViewConfig
    from phirie_jax.view.server import Viewer

    out = converted_folder(tmp_path_factory.mktemp("view"))
    viewer = Viewer(out, ViewConfig(port=free_port()))
    yield viewer
    viewer.close()


def _object_screen_points(viewer, client) -> dict[int, tuple[float, float]]:
    """Each object's Gaussian centre now, in the client's view (0–1 screen coordinates)."""
    camera = client.camera
    view = CameraView(float(camera.fov), float(camera.aspect), np.asarray(camera.wxyz), np.asarray(camera.position))
    points = {}
    for object_id, wxyz, position in viewer.live.motions():
        from scipy.spatial.transform import Rotation

        centre0 = viewer.objects[object_id].centers.astype(np.float64).mean(0)
        centre = Rotation.from_quat(wxyz, scalar_first=True).apply(centre0) + position
        found = screen_position(centre, view)
        if found is not None and 0.05 < found[0] < 0.95 and 0.05 < found[1] < 0.95:
            points[object_id] = found
    return points


def positions(viewer) -> dict[int, np.ndarray]:
    """Each object's displacement since t = 0 on the server."""
    return {object_id: position.copy() for object_id, _, position in viewer.live.motions()}


def _image(png: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).astype(np.float64)


def test_page_draws_the_objects_a_click_shoots_one_and_a_drag_pulls_another(viewer, tmp_path):
    with sync_playwright() as playwright:
        context = playwright.chromium.launch_persistent_context(
            str(tmp_path / "profile"), executable_path=CHROMIUM, headless=True, args=FLAGS, viewport=VIEWPORT)
        try:
            page = context.new_page()
            page.goto(viewer.url)
            client = until(lambda: next(iter(viewer.server.get_clients().values()), None), "the page to connect")
            canvas = page.locator("canvas").first
            canvas.wait_for(state="visible", timeout=WAIT_S * 1000)
            box = until(canvas.bounding_box, "the canvas")
            points = until(lambda: _object_screen_points(viewer, client), "the view to show the objects")
            pixels = {i: (int(box["x"] + u * box["width"]), int(box["y"] + v * box["height"]))
                      for i, (u, v) in points.items()}

            def screen(name: str) -> np.ndarray:
                return _image(page.screenshot(path=str(tmp_path / f"{name}.png")))

            # the background alone first, then the objects appear where they project: polled, as
            # software WebGL draws (and sorts the splats) at its own pace
            viewer.toggles["Background only"].value = True
            until(lambda: not any(viewer._nodes[f"object {i}"].visible for i in viewer.live.object_ids),
                  "the objects to be hidden")
            until(lambda: screen("background_only").std() > BLANK_STD, "the background to be drawn (the page is blank)")
            page.wait_for_timeout(1000)
            hidden = screen("background_only")
            viewer.toggles["Background only"].value = False

            def objects_drawn():
                shown = screen("scene")
                change = {i: np.abs(shown[y - 6:y + 7, x - 6:x + 7] - hidden[y - 6:y + 7, x - 6:x + 7]).mean()
                          for i, (x, y) in pixels.items()}
                return change if all(c > OBJECT_CHANGE for c in change.values()) else None

            until(objects_drawn, "every object's pixels to change when it is shown")

            page.wait_for_timeout(1500)
            order = sorted(points.items(), key=lambda item: item[1][0])  # left to right, clear of the panel
            target, (u, v) = order[0]
            before = positions(viewer)
            page.mouse.click(box["x"] + u * box["width"], box["y"] + v * box["height"])
            shot = until(lambda: viewer.live.shots[-1] if viewer.live.shots else None, "the click to reach the server")
            assert shot["hit"] == target, shot
            until(lambda: np.linalg.norm(positions(viewer)[target] - before[target]) > MOVED_M,
                  "the shot object to move")

            dragged, (u, v) = order[-1]   # drag the other one leftwards: it follows the pointer
            x, y = box["x"] + u * box["width"], box["y"] + v * box["height"]
            before = positions(viewer)
            page.mouse.move(x, y)
            page.mouse.down()
            for step in range(1, DRAG_STEPS + 1):
                page.mouse.move(x - DRAG_PX * step / DRAG_STEPS, y)
                page.wait_for_timeout(50)
            until(lambda: dragged in viewer.live.grabs, "the drag to grab the object")
            page.wait_for_timeout(800)
            page.mouse.up()
            until(lambda: not viewer.live.grabs, "the drag to end")
            moved = positions(viewer)[dragged] - before[dragged]
            assert np.linalg.norm(moved) > MOVED_M, moved
        finally:
            context.close()
