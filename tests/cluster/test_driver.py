"""``phirie convert-many``'s parts that need no Ray instance: the scenes' names, the root's checks,
the tasks' options against a cluster's resources, which failures are retried, the inputs record
that tells a converted scene from one to convert again, and the command's one-line refusals."""

from __future__ import annotations

import dataclasses
import errno
import json
import shutil
import subprocess
import sys
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from types import SimpleNamespace

import pytest

from phirie_jax import layout
from phirie_jax.cli import main
from phirie_jax.cluster.driver import Placement, check_root, scene_names, task_options
from phirie_jax.cluster.scene_task import TransientSceneError, is_transient
from phirie_jax.errors import NativeLibraryError, OptionError, SceneInputError, StageError
from phirie_jax.frame.config import FrameConfig
from phirie_jax.io.scene import load_scene
from phirie_jax.pipeline import ConvertConfig, conversion_inputs
from phirie_jax.provenance import up_to_date
from phirie_jax.synthetic import synthesize
from tests.processes import kill_quietly


@pytest.mark.parametrize("scenes, names", [
    (["/data/fox", "/data/snowmiku"], ["fox", "snowmiku"]),
    (["/a/lab1/desk", "/a/lab2/desk", "/a/shelf"], ["lab1-desk", "lab2-desk", "shelf"]),
    (["/x/lab/desk", "/y/lab/desk"], ["x-lab-desk", "y-lab-desk"]),
    (["/a/desk/point_cloud.ply", "/b/desk"], ["a-desk", "b-desk"]),
    (["/desk", "/desk/"], ["desk", "desk-2"]),
])
def test_scene_names_are_their_folders_told_apart_by_their_parents(scenes, names):
    assert scene_names([Path(s) for s in scenes]) == names


def test_a_root_that_is_a_capture_or_one_conversion_is_refused(tmp_path):
    scene = tmp_path / "scene"
    scene.mkdir()
    (tmp_path / "file").write_text("")
    with pytest.raises(OptionError, match="is a file"):
        check_root(tmp_path / "file", [scene], ["scene"])
    (tmp_path / "capture").mkdir()
    (tmp_path / "capture" / "point_cloud.ply").write_text("")
    with pytest.raises(OptionError, match=r"holds a capture's inputs \(point_cloud.ply\)"):
        check_root(tmp_path / "capture", [scene], ["scene"])
    (tmp_path / "one").mkdir()
    (tmp_path / "one" / layout.MANIFEST).write_text('{"schema": "phirie/1"}')
    with pytest.raises(OptionError, match="one conversion's output"):
        check_root(tmp_path / "one", [scene], ["scene"])
    with pytest.raises(OptionError, match="inside the scene folder"):   # ROOT/scene would lie in the scene
        check_root(scene, [scene], ["scene"])
    check_root(tmp_path / "new", [scene], ["scene"])
    assert not (tmp_path / "new").exists()


def fake_ray(**resources) -> SimpleNamespace:
    return SimpleNamespace(cluster_resources=lambda: {"CPU": 8.0, "memory": 1e10, "node:10.0.0.1": 1.0, **resources})


def test_tasks_ask_for_a_gpu_when_the_cluster_has_one():
    assert task_options(fake_ray(), Placement())["num_gpus"] == 0
    options = task_options(fake_ray(GPU=2.0), Placement(retries=3))
    assert options["num_gpus"] == 1 and options["num_cpus"] == 1 and options["max_retries"] == 3
    assert options["retry_exceptions"] == [TransientSceneError] and "runtime_env" not in options
    shared = task_options(fake_ray(GPU=1.0), Placement(gpus=0.5))
    assert shared["num_gpus"] == 0.5 and shared["runtime_env"]["env_vars"] == {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
    assert task_options(fake_ray(GPU=1.0), Placement(gpus=0))["num_gpus"] == 0


def test_resources_the_cluster_lacks_are_refused():
    assert task_options(fake_ray(bigmem=2.0), Placement(resources={"bigmem": 1}))["resources"] == {"bigmem": 1}
    with pytest.raises(OptionError) as err:
        task_options(fake_ray(), Placement(resources={"bigmem": 1}))
    assert str(err.value) == ("--resources bigmem=1: the cluster has 0 of 'bigmem' (expected at least 1; it has: "
                              "CPU, memory)")
    with pytest.raises(OptionError, match="--gpus-per-scene 1: the cluster has 0 GPUs"):
        task_options(fake_ray(), Placement(gpus=1))
    with pytest.raises(OptionError, match="--cpus-per-scene 9: the cluster has 8 CPUs"):
        task_options(fake_ray(), Placement(cpus=9))


@pytest.mark.parametrize("err, transient", [
    (StageError("physics", MemoryError()), True),
    (StageError("physics", BrokenProcessPool("a worker died")), True),
    (StageError("physics", NativeLibraryError("CoACD", "died with signal 9 (SIGKILL)", "SIGKILL")), True),
    (StageError("physics", NativeLibraryError("CoACD", "died with signal 11 (SIGSEGV)", "SIGSEGV")), False),
    (StageError("background", RuntimeError("RESOURCE_EXHAUSTED: Out of memory allocating 4 GiB")), True),
    (StageError("objects", ValueError("no candidate")), False),
    (OSError(errno.EIO, "Input/output error"), True),
    (OSError(errno.ENOENT, "No such file"), False),
    (SceneInputError("/s/point_cloud.ply", None, "truncated"), False),
    (OptionError("--out", "in use by process 7"), False),
])
def test_only_failures_another_attempt_may_not_meet_are_retried(err, transient):
    assert is_transient(err) == transient


@pytest.fixture(scope="module")
def desk(tmp_path_factory) -> Path:
    """A tiny synthetic scene (not changed by the tests: copy it first)."""
    root = tmp_path_factory.mktemp("captures") / "desk"
    synthesize(root, preset="tiny", seed=3)
    return root


def record(scene: Path, config: ConvertConfig | None = None, masks=None, frame: FrameConfig | None = None) -> dict:
    return conversion_inputs(load_scene(scene), config or ConvertConfig(), masks, None, frame or FrameConfig())


def test_the_inputs_record_changes_with_what_the_conversion_reads_and_its_options(desk, tmp_path):
    scene = Path(shutil.copytree(desk, tmp_path / "desk"))
    first = record(scene)
    assert first["inputs"].startswith("sha256:") and first["files"] > 20 and first["bytes"] > 0
    assert record(scene) == first
    moved = Path(shutil.move(scene, tmp_path / "elsewhere"))
    assert record(moved) == first                            # names are relative to the scene folder
    physics = ConvertConfig().physics
    workers = ConvertConfig(physics=dataclasses.replace(physics, workers=3))
    assert record(moved, workers) == first                   # how fast, not what
    lower = ConvertConfig(physics=dataclasses.replace(physics, coacd=dataclasses.replace(physics.coacd, niceness=0)))
    assert record(moved, lower) == first                     # so is the collision workers' priority
    cheaper = ConvertConfig(background=dataclasses.replace(
        ConvertConfig().background, refine=dataclasses.replace(ConvertConfig().background.refine, iterations=0)))
    assert record(moved, cheaper)["options"] != first["options"] and record(moved, cheaper)["inputs"] == first["inputs"]
    assert record(moved, masks="auto")["options"] != first["options"]
    assert record(moved, frame=FrameConfig(metric=True))["options"] != first["options"]
    declaration = (moved / "frame.json").read_text()
    (moved / "frame.json").write_text(json.dumps({**json.loads(declaration), "metric": False}))
    assert record(moved)["inputs"] != first["inputs"]          # the scene's own frame.json is read
    (moved / "frame.json").write_text(declaration)
    (moved / "prompts.json").write_text('{"prompts": []}')    # so is every file at the top of the folder
    added = record(moved)
    assert added["inputs"] != first["inputs"] and added["files"] == first["files"] + 1
    (moved / "prompts.json").unlink()
    assert record(moved) == first
    image = next((moved / "images").iterdir())
    image.write_bytes(image.read_bytes() + b"\0")
    assert record(moved)["inputs"] != first["inputs"]


def test_a_folder_is_up_to_date_only_when_complete_from_the_same_inputs(desk, tmp_path):
    from phirie_jax.manifest import Manifest

    inputs = record(desk)
    out = tmp_path / "out"
    assert not up_to_date(out, inputs)
    manifest = Manifest(out)
    for name in ("frame", "observe", "objects", "physics", "background"):
        manifest.mark_stage(name, "complete")
    manifest.set("inputs", inputs)
    manifest.write()
    assert up_to_date(out, inputs)
    assert not up_to_date(out, {**inputs, "options": "sha256:other"})
    manifest.mark_stage("physics", "running")
    manifest.write()
    assert not up_to_date(out, inputs)


def test_without_ray_the_command_says_how_to_install_it(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)   # import ray raises ImportError
    assert main(["convert-many", str(tmp_path / "scene"), "--out", str(tmp_path / "root")]) == 2
    assert capsys.readouterr().err == ("phirie: error: phirie convert-many: needs Ray (expected it installed: "
                                       "pip install 'phirie_jax[cluster]')\n")
    assert not (tmp_path / "root").exists()


@pytest.mark.parametrize("options, message", [
    (["--resources", "bigmem"], "--resources: 'bigmem' (expected NAME=AMOUNT with a positive amount, e.g. bigmem=1)"),
    (["--workers", "2", "--address", "auto"],
     "--workers: sets the CPUs of a local Ray instance (expected no --address; a running cluster has its own)"),
    (["--workers", "0"], "--workers 0: expected ≥ 1"),
])
def test_bad_options_are_refused_in_one_line(options, message, tmp_path, capsys):
    pytest.importorskip("ray")
    assert main(["convert-many", str(tmp_path / "scene"), "--out", str(tmp_path / "root"), *options]) == 2
    assert capsys.readouterr().err == f"phirie: error: {message}\n"
    assert not (tmp_path / "root").exists()


def test_a_scene_given_twice_is_refused(tmp_path, capsys):
    pytest.importorskip("ray")
    (tmp_path / "scene").mkdir()
    assert main(["convert-many", str(tmp_path / "scene"), str(tmp_path / "scene"), "--out", str(tmp_path / "root")]) == 2
    assert capsys.readouterr().err == f"phirie: error: {tmp_path / 'scene'}: given twice (expected each scene once)\n"


def test_a_root_another_run_holds_is_refused_before_ray_starts(tmp_path, capsys):
    pytest.importorskip("ray")
    root = tmp_path / "root"
    hold = ("import sys, time\nfrom phirie_jax.io.output_folder import locked\n"
            "with locked(sys.argv[1]):\n print('held', flush=True)\n time.sleep(60)")
    holder = subprocess.Popen([sys.executable, "-c", hold, str(root)], stdout=subprocess.PIPE)
    try:
        assert holder.stdout.readline() == b"held\n"
        assert main(["convert-many", str(tmp_path / "scene"), "--out", str(root)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"phirie: error: --out {root}: in use by process {holder.pid} on ") and \
            err.count("\n") == 1
        assert "ray" not in sys.modules or not sys.modules["ray"].is_initialized()
    finally:
        kill_quietly(holder.pid)
        holder.wait()
