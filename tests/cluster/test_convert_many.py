"""``phirie convert-many`` on a local Ray instance of 2 CPUs (loopback only).

One run converts three ``tiny`` synthetic scenes (two of them in folders of the same name) and a
corrupt one, while the test kills the worker process converting the first scene in the middle of
its objects stage. Checked on that run: the three scenes convert, the corrupt one is recorded with
its reason and does not stop the others, the killed scene is retried and completes, and its
``scene.xml`` and ``background.ply`` equal, byte for byte, those of converting it alone with
``phirie convert``. A second run on the same root skips the scenes already converted from the same
inputs with the same options and still fails the corrupt one; one whose conversion did not finish
is converted again (``-m slow``, as are the comparisons of the two other scenes with their
conversions alone).

The run is made once per test session (``shared_once``), also when pytest-xdist spreads this
module's tests over several processes.
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from phirie_jax import layout
from phirie_jax.cli import main
from phirie_jax.manifest import Manifest
from phirie_jax.synthetic import synthesize
from tests.fixtures.cheap_convert import CHEAP
from tests.processes import running, wait_for

pytest.importorskip("ray", reason="the cluster extra (pip install 'phirie_jax[cluster]') is not installed")

RUN_SECONDS = 900        # the 4-scene run (one killed and retried) on a loaded 2-core machine
BUSY_SECONDS = 300       # until the first scene's objects stage runs
NAMES = ["lab1-desk", "lab2-desk", "shelf", "broken"]
KILLED = "lab1-desk"
OUTPUTS = (layout.SCENE_MJCF, layout.BACKGROUND)


def shared_once(tmp_path_factory, name: str, make) -> Path:
    """``make(folder)`` run once per test session into ``folder``, which is returned; with
    pytest-xdist the workers share it (the first makes it under a lock, the others wait and read)."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        folder = tmp_path_factory.mktemp(name)
        make(folder)
        return folder
    base = tmp_path_factory.getbasetemp().parent   # this session's, shared by its workers
    folder = base / name
    with open(base / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (folder / "made").is_file():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            make(folder)
            (folder / "made").write_text("")
    return folder


def make_captures(root: Path) -> list[Path]:
    """Three tiny scenes (two named ``desk``) and a copy of one whose Gaussian PLY is cut short."""
    scenes = [root / "lab1" / "desk", root / "lab2" / "desk", root / "shelf", root / "broken"]
    for scene, seed in zip(scenes, (3, 4, 5)):
        synthesize(scene, preset="tiny", seed=seed)
    shutil.copytree(scenes[2], scenes[3])
    ply = scenes[3] / "point_cloud.ply"
    ply.write_bytes(ply.read_bytes()[: ply.stat().st_size // 2])
    return scenes


def stage_status(out: Path) -> dict:
    try:
        return json.loads((out / layout.MANIFEST).read_text()).get("stages") or {}
    except (OSError, ValueError):
        return {}


def lock_pid(out: Path) -> int | None:
    try:
        return int(json.loads((out / layout.LOCK).read_text())["pid"])
    except (OSError, ValueError, KeyError):
        return None


def convert_many_killing_a_worker(folder: Path) -> None:
    """The run (module docstring), in a child process; the worker converting ``KILLED`` is killed
    with SIGKILL once its objects stage runs. Writes ``run.json``: exit code, output, killed pid."""
    scenes = make_captures(folder / "captures")
    root = folder / "root"
    run = subprocess.Popen([sys.executable, "-m", "phirie_jax.cli", "convert-many", *map(str, scenes), "--out",
                            str(root), "--workers", "2", *CHEAP], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                           start_new_session=True)
    out = root / KILLED
    killed = None
    try:
        if wait_for(lambda: stage_status(out).get("objects") == "running" and lock_pid(out) or run.poll() is not None,
                    BUSY_SECONDS) and run.poll() is None:
            killed = lock_pid(out)
            os.kill(killed, signal.SIGKILL)
        stdout, stderr = run.communicate(timeout=RUN_SECONDS)
    finally:
        if run.poll() is None:
            os.killpg(run.pid, signal.SIGKILL)
            run.wait()
    (folder / "run.json").write_text(json.dumps({"code": run.returncode, "stdout": stdout.decode(),
                                                 "stderr": stderr.decode(), "killed": killed,
                                                 "scenes": [str(s) for s in scenes]}))


@pytest.fixture(scope="module")
def many(tmp_path_factory) -> tuple[dict, Path, dict]:
    """(what the run did: code, stdout, stderr, killed pid, scenes; its root; summary.json)."""
    folder = shared_once(tmp_path_factory, "convert_many", convert_many_killing_a_worker)
    run = json.loads((folder / "run.json").read_text())
    summary_path = folder / "root" / "summary.json"
    assert summary_path.is_file(), run
    return run, folder / "root", json.loads(summary_path.read_text())


def records(summary: dict) -> dict[str, dict]:
    return {r["name"]: r for r in summary["scenes"]}


def test_three_tiny_scenes_convert(many):
    run, root, summary = many
    assert run["code"] == 1, run["stderr"]    # the corrupt scene failed; the others did not
    assert [r["name"] for r in summary["scenes"]] == NAMES
    assert summary["counts"] == {"converted": 3, "failed": 1}
    assert summary["address"] == "local" and summary["cluster"]["CPU"] == 2
    assert summary["task"] == {"num_cpus": 1, "num_gpus": 0, "max_retries": 2, "resources": {}}
    for name in NAMES[:3]:
        r = records(summary)[name]
        assert r["status"] == "converted" and r["reason"] is None, r
        assert sum(r["objects"].values()) == 3 and r["objects"]["failed"] == 0, r
        assert r["drop_tests"]["tested"] == r["objects"]["accepted"] + r["objects"]["unverified"], r
        assert r["background"]["gaussians"] == (r["background"]["source_gaussians"] - r["background"]["removed"]
                                                + r["background"]["filled"]), r
        assert r["frame"]["scale_source"] and r["frame"]["up_source"], r
        assert r["seconds"] >= r["convert_seconds"] - 0.01 > 0 and r["peak_memory_mb"] > 100, r
        out = root / name
        assert Manifest.load_or_create(out).unfinished() == {}
        assert all((out / f).is_file() for f in OUTPUTS) and not (out / layout.LOCK).exists()
        assert not list(out.rglob("*.tmp")), "a temporary was left behind"
    assert not (root / layout.LOCK).exists()
    lines = run["stdout"].splitlines()
    assert lines[0] == "phirie: 4 scenes on a local Ray instance (2 CPUs, 0 GPUs; each scene 1 CPU, 0 GPU)"
    for name in NAMES[:3]:
        assert any(line.startswith(f"phirie: {name}: converted in ") for line in lines), run["stdout"]
    assert lines[-1] == f"summary: {root / 'summary.json'}"
    assert run["stderr"].splitlines()[-1] == (f"phirie: error: 1 of 4 scenes failed (reasons in "
                                              f"{root / 'summary.json'})")


def test_a_corrupt_scene_is_recorded_and_the_others_go_on(many):
    run, root, summary = many
    broken = records(summary)["broken"]
    ply = Path(run["scenes"][3]) / "point_cloud.ply"
    assert broken["status"] == "failed" and broken["reason"].startswith(f"{ply}: "), broken
    assert broken["objects"] is None and not (root / "broken").exists()   # nothing half-written for it
    assert "phirie: broken: failed in " in run["stdout"] and broken["reason"] in " ".join(run["stdout"].split())


def test_a_killed_worker_loses_no_scene(many):
    run, _, summary = many
    assert run["killed"] is not None, "the worker was not killed: the run ended before its objects stage"
    assert not running(run["killed"])
    r = records(summary)[KILLED]
    assert r["status"] == "converted" and r["took_over"] == run["killed"] and r["pid"] != run["killed"], r
    assert f"after taking over from killed process {run['killed']}" in run["stdout"]


@pytest.mark.parametrize("name", [KILLED, pytest.param("lab2-desk", marks=pytest.mark.slow),
                                  pytest.param("shelf", marks=pytest.mark.slow)])
def test_each_scene_equals_its_conversion_alone(many, name, tmp_path):
    run, root, _ = many
    scene = Path(run["scenes"][NAMES.index(name)])
    assert main(["convert", str(scene), "--out", str(tmp_path / "alone"), *CHEAP]) == 0
    for output in OUTPUTS:
        assert (root / name / output).read_bytes() == (tmp_path / "alone" / output).read_bytes(), output


def rerun(run: dict, root: Path, folder: Path) -> tuple[int, dict]:
    """``convert-many`` again, as the first run was, on a copy of its root: (exit code, summary)."""
    again = Path(shutil.copytree(root, folder, symlinks=True))
    code = main(["convert-many", *run["scenes"], "--out", str(again), "--workers", "2", *CHEAP])
    return code, json.loads((again / "summary.json").read_text())


# The rerun starts Ray from this process, where an earlier test's conversion started JAX: JAX warns
# at every fork, but Ray's processes exec at once and run none of this process's threads' code.
@pytest.mark.filterwarnings(r"ignore:os\.fork\(\) was called:RuntimeWarning")
def test_a_rerun_skips_the_converted_scenes(many, tmp_path, capsys):
    run, root, summary = many
    code, again = rerun(run, root, tmp_path / "root")
    assert code == 1 and [r["status"] for r in again["scenes"]] == ["skipped"] * 3 + ["failed"]
    for name in NAMES[:3]:
        skipped, first = records(again)[name], records(summary)[name]
        assert {k: skipped[k] for k in ("objects", "drop_tests", "background", "frame", "convert_seconds")} == \
            {k: first[k] for k in ("objects", "drop_tests", "background", "frame", "convert_seconds")}
        assert (tmp_path / "root" / name / layout.MANIFEST).read_bytes() == (root / name / layout.MANIFEST).read_bytes()
    assert records(again)["broken"]["reason"] == records(summary)["broken"]["reason"]
    out = capsys.readouterr().out
    assert all(f"phirie: {name}: skipped in " in out for name in NAMES[:3]), out


@pytest.mark.slow
def test_a_rerun_converts_a_scene_whose_conversion_did_not_finish(many, tmp_path):
    run, root, _ = many
    unfinished = root / "shelf"
    before = {output: (unfinished / output).read_bytes() for output in OUTPUTS}

    def killed_in_its_last_stage(folder: Path) -> None:
        manifest = Manifest.load_or_create(folder)
        manifest.mark_stage("background", "running")
        manifest.write()
        (folder / layout.LOCK).write_text(json.dumps({"pid": 2 ** 22 + 9, "host": "elsewhere"}))

    copy = Path(shutil.copytree(root, tmp_path / "copy", symlinks=True))
    killed_in_its_last_stage(copy / "shelf")
    code, again = rerun(run, copy, tmp_path / "root")
    status = {r["name"]: r["status"] for r in again["scenes"]}
    assert code == 1 and status == {"lab1-desk": "skipped", "lab2-desk": "skipped", "shelf": "converted",
                                    "broken": "failed"}
    assert records(again)["shelf"]["took_over"] == 2 ** 22 + 9
    resumed = tmp_path / "root" / "shelf"
    assert {output: (resumed / output).read_bytes() for output in OUTPUTS} == before
    assert Manifest.load_or_create(resumed).unfinished() == {}
