"""The small real fixture cut from the fox capture (``experiments/make_fox_fixture.py``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from phirie_jax.io.scene import load_scene
from phirie_jax.observe.box_prompt import BoxPrompt
from phirie_jax.observe.masks import read_label_png

FOX = Path(__file__).resolve().parent / "fixtures" / "fox"
HELD_OUT = {"0001.jpg", "0012.jpg", "0027.jpg", "0042.jpg", "0073.jpg", "0089.jpg", "0110.jpg"}
MAX_BYTES = 4 * 1024 * 1024
MAX_GAUSSIANS = 15_000
MIN_MASK_PIXELS = 500   # of 135×240: the head covers 5–10K pixels in every view when made


def test_fixture_loads_as_a_scene():
    scene = load_scene(FOX)
    assert scene.layout == "nerfstudio"
    assert 8 <= len(scene.cameras) <= 12
    assert not HELD_OUT & {c.name for c in scene.cameras}
    assert all((c.width, c.height) == (135, 240) for c in scene.cameras)
    assert 0 < scene.gaussians.num <= MAX_GAUSSIANS and scene.gaussians.sh_degree == 1
    assert scene.masks is not None and all(p is not None for p in scene.masks)


def test_fixture_is_small_and_carries_the_licence():
    size = sum(p.stat().st_size for p in FOX.rglob("*") if p.is_file())
    assert size <= MAX_BYTES
    assert "NVIDIA" in (FOX / "LICENSE.txt").read_text()
    assert "degree 1" in (FOX / "README.md").read_text()


def test_head_masks_are_non_empty_in_most_views():
    scene = load_scene(FOX)
    areas = [int((read_label_png(p, c) == 1).sum()) for c, p in zip(scene.cameras, scene.masks)]
    values = set()
    for c, p in zip(scene.cameras, scene.masks):
        values |= set(np.unique(read_label_png(p, c)).tolist())
    assert values <= {0, 1}
    assert sum(a >= MIN_MASK_PIXELS for a in areas) >= 0.8 * len(areas), areas


def test_box_prompt_reads_back_and_holds_the_head():
    prompt = json.loads((FOX / "box_prompt.json").read_text())
    box = BoxPrompt(prompt["id"], tuple(prompt["lower"]), tuple(prompt["upper"]),
                    tuple(tuple(r) for r in prompt["rotation"]))
    g = load_scene(FOX).gaussians
    inside = box.contains(g.means.astype(np.float64))
    assert 0.1 < inside.mean() < 0.9   # the head, with wall around it


FRAME_REASON = ("the fixture is in the capture's non-metric, tilted frame: observation's metric "
                "constants (2 cm association voxels) find no instance until the scene-frame step "
                "resolves metres and up (then enable)")


@pytest.mark.slow
@pytest.mark.xfail(strict=False, reason=FRAME_REASON)
@pytest.mark.parametrize("masks", ["files", "auto"])
def test_fixture_converts_to_a_scene_with_the_head(tmp_path, masks):
    from phirie_jax.pipeline import run_convert

    manifest = run_convert(FOX, tmp_path / "out", masks=masks)
    assert manifest["instances"], "no instance observed"
    accepted = [o for o in manifest["objects"] if o["status"] == "accepted"]
    assert accepted, [o.get("reason") for o in manifest["objects"]]
    assert manifest["background"]["removed"] > 0
    frame = manifest.get("frame") or {}
    assert frame.get("capture_to_world") is not None
