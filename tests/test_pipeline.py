"""``phirie convert`` end to end on the tiny synthetic preset: every stage runs, the output folder
is the one docs/architecture.md describes, and the Interactive Environment loads and renders it."""

from __future__ import annotations

import dataclasses
import json

import mujoco
import numpy as np
import pytest

from phirie_jax.cli import main
from phirie_jax.io.ply import read_gaussian_ply
from phirie_jax.pipeline import STAGES
from phirie_jax.synthetic import synthesize
from tests.fixtures.cheap_convert import CHEAP_COLLISION, CHEAP_PHYSICS

PLACEMENT_TOL = 0.03  # m between a placed object's origin and the true one's


@pytest.fixture(scope="module")
def converted(tmp_path_factory):
    root = tmp_path_factory.mktemp("convert")
    scene = synthesize(root / "scene", preset="tiny", seed=3)
    assert main(["convert", str(root / "scene"), "--out", str(root / "out"), *CHEAP_COLLISION]) == 0
    return scene, root / "scene", root / "out"


def test_every_stage_writes_its_part_of_the_output_folder(converted):
    scene, _, out = converted
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["schema"] == "phirie/1"
    assert set(STAGES) | {"convert"} <= set(manifest["timings"])
    assert {i["id"] for i in manifest["instances"]} == {o.id for o in scene.objects}
    accepted = [o for o in manifest["objects"] if o["status"] == "accepted"]
    assert accepted
    for obj in accepted:
        for path in (obj["mesh"], obj["visual"], obj["physics"]["urdf"]):
            assert (out / path).is_file(), (obj["id"], path)
        assert obj["collision"] and all((out / p).is_file() for p in obj["collision"])
        assert {"stable", "drift_m", "final_height_m"} <= set(obj["drop_test"])
    model = mujoco.MjModel.from_xml_path(str(out / "scene.xml"))
    assert {f"object_{o['id']}" for o in accepted} <= {model.body(b).name for b in range(model.nbody)}
    assert (out / "transforms.json").is_file()


def test_background_has_the_accepted_objects_removed_and_their_footprint_filled(converted):
    _, scene_dir, out = converted
    manifest = json.loads((out / "manifest.json").read_text())
    b = manifest["background"]
    capture = read_gaussian_ply(scene_dir / "point_cloud.ply")
    background = read_gaussian_ply(out / b["path"])
    assert background.num == capture.num - b["removed"] + b["filled"] and b["removed"] > 0 and b["filled"] > 0
    assert np.isfinite(background.means).all() and np.isfinite(background.sh).all()
    status = {o["id"]: o["status"] for o in b["objects"]}
    for obj in manifest["objects"]:
        if obj["status"] == "accepted":
            assert status[obj["id"]] == "filled", b["objects"]


def test_objects_are_placed_where_the_truth_is(converted):
    _, scene_dir, out = converted
    truth = {o["id"]: np.asarray(o["pose"]) for o in json.loads((scene_dir / "gt" / "objects.json").read_text())}
    manifest = json.loads((out / "manifest.json").read_text())
    for obj in manifest["objects"]:
        if obj["status"] == "accepted":
            err = np.linalg.norm(np.asarray(obj["pose"])[:3, 3] - truth[obj["id"]][:3, 3])
            assert err < PLACEMENT_TOL, (obj["id"], err)


def test_environment_renders_the_converted_scene_close_to_the_capture(converted):
    from phirie_jax.interact.environment import Environment
    from phirie_jax.render import render

    _, scene_dir, out = converted
    env = Environment.load(out)
    camera = env.camera(0)
    now = env.render(camera)
    captured = render(read_gaussian_ply(scene_dir / "point_cloud.ply").to_kernel(), camera)
    a, c = np.asarray(now.alpha), np.asarray(captured.alpha)
    assert np.isfinite(np.asarray(now.rgb)).all()
    # the converted scene covers the image where the capture did (objects + filled table)
    assert np.mean(np.abs(a - c) > 0.5) < 0.02


def test_an_object_physics_fails_stays_in_the_background(converted, tmp_path, monkeypatch):
    """The background runs beside the collision assuming every accepted object stays; an object
    whose collision then fails gets the background built again, with its Gaussians kept."""
    import shutil

    from phirie_jax.construct.physics import stage
    from phirie_jax.construct.physics.collision import MeshError
    from phirie_jax.pipeline import ConvertConfig, run_convert

    _, scene_dir, out = converted
    before = json.loads((out / "manifest.json").read_text())
    failing = next(o["id"] for o in before["objects"] if o["status"] == "accepted")
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    build = stage.build_object

    def build_or_fail(entry, *args):
        if entry["id"] == failing:
            raise MeshError("made to fail by the test")
        return build(entry, *args)

    monkeypatch.setattr(stage, "build_object", build_or_fail)
    config = ConvertConfig(physics=dataclasses.replace(CHEAP_PHYSICS, workers=1))   # built in this process, where the patch holds
    manifest = run_convert(scene_dir, copy, config, stages=("physics", "background"))
    status = {o["id"]: o["status"] for o in manifest["objects"]}
    assert status[failing] == "failed"
    records = {o["id"]: o for o in manifest["background"]["objects"]}
    assert records[failing]["status"] == "skipped"
    b, b0 = manifest["background"], before["background"]
    assert b["removed"] < b0["removed"]
    capture = read_gaussian_ply(scene_dir / "point_cloud.ply")
    assert read_gaussian_ply(copy / b["path"]).num == capture.num - b["removed"] + b["filled"]


def test_a_run_moves_its_capture_once_per_frame_and_shares_it_with_the_runs_derived_from_it():
    import types
    from pathlib import Path

    from phirie_jax.pipeline import ConvertConfig, Run

    moves = []

    def frame():
        return types.SimpleNamespace(apply=lambda capture: moves.append(capture) or f"{capture} in the world")

    run = Run("capture", Path("out"), ConvertConfig())
    with pytest.raises(RuntimeError, match="frame stage"):
        run.scene
    run = dataclasses.replace(run, frame=frame())
    assert run.scene == "capture in the world" and len(moves) == 1
    derived = dataclasses.replace(run, kept=frozenset({1}))       # as the collision job's start derives one
    assert derived.scene is run.scene and len(moves) == 1
    rescaled = dataclasses.replace(derived, frame=frame())        # --known-size: a new frame moves it again
    assert rescaled.scene == "capture in the world" and len(moves) == 2
