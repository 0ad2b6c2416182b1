"""The small real fixture cut from the fox capture (``experiments/make_fox_fixture.py``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from phirie_jax.info import outcome_lines
from phirie_jax.io.ply import read_gaussian_ply
from phirie_jax.io.scene import load_scene
from phirie_jax.manifest import Manifest
from phirie_jax.observe.box_prompt import BoxPrompt
from phirie_jax.observe.masks import read_label_png
from phirie_jax.pipeline import ConvertConfig, run_convert
from tests.fixtures.cheap_convert import CHEAP_PHYSICS

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


# CoACD's search shortened: the head's collision is not what these tests are about
QUICK = ConvertConfig(physics=CHEAP_PHYSICS)


def test_automatic_masks_say_why_nothing_stands_on_a_support(tmp_path):
    """A wall-mounted head has no horizontal support under it: the run completes, finds no
    instance, and says so."""
    manifest = run_convert(FOX, tmp_path / "out", QUICK, masks="auto")
    assert manifest["instances"] == [] and manifest["objects"] == []
    assert manifest["frame"]["scale_source"].startswith("prior: ") and manifest["frame"]["scale_uncertainty"] > 1
    lines = outcome_lines(Manifest.load(tmp_path / "out"))
    assert any(line.startswith("no object instance found: no support plane") for line in lines), lines


@pytest.mark.slow   # heavy: a whole conversion with CoACD of the 60K-triangle head
def test_a_users_masks_make_the_head_an_asset(tmp_path):
    manifest = run_convert(FOX, tmp_path / "out", QUICK, masks="files")
    frame = manifest["frame"]
    assert 0.03 < frame["scale"] < 1.0 and frame["up"] == [0.0, 0.0, 1.0]   # the prior's metres, not units
    assert [i["id"] for i in manifest["instances"]] == [1]
    (head,) = manifest["objects"]
    # kept as a body; on this cut-down capture the built-in shapes miss the head by more than the
    # registration check's 1 cm, and the head (cut from its mount, its mass over the cut) may tip
    # in the drop test depending on its CoACD parts: the status says both
    assert head["status"] == ("unverified" if head["unresolved_checks"] else "accepted"), head.get("reason")
    assert set(head["unresolved_checks"]) <= {"registration", "settling"}, head["unresolved_checks"]
    if "settling" in head["unresolved_checks"]:
        assert head["drop_test"]["stable"] is False and head["checks"]["settling"]["passed"] is False
    assert head["checks"]["scale"]["passed"] and head["checks"]["support"]["passed"]
    assert read_gaussian_ply(tmp_path / "out" / head["visual"]).num > 1000
    assert manifest["background"]["removed"] > 3000   # the head's source Gaussians left the background


def test_a_prompt_on_the_head_finds_the_wall_it_is_mounted_on(tmp_path):
    """One box around the head in one photo: the lift finds the wall behind it, the head hangs
    above the support found under it, so it is mounted (its settling left to the hold test)."""
    manifest = run_convert(FOX, tmp_path / "out", QUICK, stages=("observe", "objects"),
                           prompts=["0019.jpg:33,24,111,174=fox head"])
    (instance,) = manifest["instances"]
    wall = instance["wall"]
    assert abs(wall["normal"][2]) < 0.1 and 0.0 < wall["gap_m"] < 0.03      # vertical, the head just in front of it
    (head,) = manifest["objects"]
    assert head["mount"] == wall and head["support"]["gap_m"] > 0.03
    assert head["checks"]["mount"]["passed"]
    assert head["checks"]["settling"]["passed"] is None and "weld" in head["checks"]["settling"]["reason"]
