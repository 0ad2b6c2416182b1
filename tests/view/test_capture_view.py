"""``phirie view SCENE`` on a capture before conversion (server side, no browser): a click on an
object makes an ``IMAGE:U,V`` prompt on that object, saved in ``SCENE/prompts.json`` with the
file's own prompts kept; undo takes back only this session's; ``phirie convert`` reads it."""

from __future__ import annotations

import json
import shutil
import socket

import numpy as np
import pytest

from phirie_jax.io.scene import load_scene
from phirie_jax.observe.masks import read_label_png
from phirie_jax.observe.raycast import pixel_rays
from phirie_jax.view.capture import PromptPicker

OBJECT_PIXELS = {1: (11, 50), 2: (47, 48)}     # (col, row) on objects 1 and 2 in camera 0 of the tiny preset


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from phirie_jax.synthetic import synthesize

    root = tmp_path_factory.mktemp("capture") / "scene"
    synthesize(root, preset="tiny")
    return root


def _ray(camera, col: int, row: int):
    origins, dirs = pixel_rays(camera, np.array([row]), np.array([col]))
    return origins[0], dirs[0]


def _label_at(scene, image: str, u: float, v: float) -> int:
    view = [c.name for c in scene.cameras].index(image)
    labels = read_label_png(scene.masks[view], scene.cameras[view])
    return int(labels[int(v), int(u)])


def test_a_click_on_an_object_gives_a_photo_point_on_that_object(tiny):
    scene = load_scene(tiny)
    picker = PromptPicker(scene.gaussians, scene.cameras)
    for ident, (col, row) in OBJECT_PIXELS.items():
        hit = picker.hit(*_ray(scene.cameras[0], col, row))
        assert hit is not None
        # the click through camera 0's pixel, and the same point clicked from camera 4's side
        for origin, direction in (_ray(scene.cameras[0], col, row), (scene.cameras[4].center, hit - scene.cameras[4].center)):
            prompt, said = picker.prompt_at(origin, direction, "thing")
            assert prompt is not None and prompt.label == "thing", said
            assert _label_at(scene, prompt.image, *prompt.point) == ident, (ident, prompt)
    nothing, said = picker.prompt_at(scene.cameras[0].center, -scene.cameras[0].world_to_camera[2, :3])
    assert nothing is None and "no opaque Gaussian" in said


def test_the_viewer_saves_a_click_merges_the_file_and_undoes_its_own(tiny, tmp_path):
    pytest.importorskip("viser", reason="viser is not installed (the viewer extra)")
    from phirie_jax.view.capture import CaptureViewer
    from phirie_jax.view.config import ViewConfig

    root = tmp_path / "scene"
    shutil.copytree(tiny, root)
    theirs = {"image": "0005.png", "box": [10, 20, 40, 60], "label": "mug"}
    (root / "prompts.json").write_text(json.dumps({"prompts": [theirs], "by": "hand"}))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    viewer = CaptureViewer(root, ViewConfig(port=port))
    try:
        scene = viewer.scene
        viewer._label.value = "bottle"
        prompt = viewer.click(*_ray(scene.cameras[0], *OBJECT_PIXELS[1]))
        assert prompt is not None and prompt.label == "bottle"
        data = json.loads((root / "prompts.json").read_text())
        assert data["by"] == "hand" and data["prompts"] == [theirs, prompt.as_json()]
        assert _label_at(load_scene(root), prompt.image, *prompt.point) == 1
        viewer._label.value = ""
        second = viewer.click(*_ray(scene.cameras[0], *OBJECT_PIXELS[2]))
        assert second is not None and second.label is None
        assert viewer.click(scene.cameras[0].center, -scene.cameras[0].world_to_camera[2, :3]) is None
        viewer.undo()
        viewer.undo()
        viewer.undo()                               # nothing of this session left: the file's own stays
        assert json.loads((root / "prompts.json").read_text())["prompts"] == [theirs]
        viewer.click(*_ray(scene.cameras[0], *OBJECT_PIXELS[2]))
    finally:
        viewer.close()
    assert sorted(p.name for p in root.iterdir()) == sorted([p.name for p in tiny.iterdir()] + ["prompts.json"])
    from phirie_jax.observe.prompts import scene_prompts

    prompts, source = scene_prompts(root, load_scene(root).cameras)
    assert source == root / "prompts.json" and [p.kind for p in prompts] == ["box", "point"]
