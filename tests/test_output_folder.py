"""The output folder's safety rules (``io.output_folder``): a conversion never writes into another
capture, into its own scene folder or over files no run of ours wrote; one run holds a folder at a
time; a killed conversion is never taken for a converted folder; images and masks that are links
leading outside the scene follow the outside-paths rule.

The scenes are the ``tiny`` synthetic preset (two captures, seeds 3 and 4). Runs that would go on
run the frame stage only (it writes the manifest and ``transforms.json``, the file a conversion
into another capture overwrote); the lock and kill tests run whole conversions in a child process.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from phirie_jax import layout, pipeline
from phirie_jax.cli import main
from phirie_jax.errors import OptionError, SceneInputError
from phirie_jax.io.camera import outside_paths_allowed
from phirie_jax.io.scene import load_scene
from phirie_jax.synthetic import synthesize
from tests.fixtures.cheap_convert import CHEAP
from tests.processes import kill_quietly, wait_for

CONVERSION_SECONDS = 240    # a whole tiny conversion in a child process on a loaded 2-core machine


@pytest.fixture(scope="module")
def captures(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("captures")
    synthesize(root / "a", preset="tiny", seed=3)
    synthesize(root / "b", preset="tiny", seed=4)
    return root / "a", root / "b"


@pytest.fixture
def scene(captures, tmp_path) -> Path:
    """A private copy of capture A (tests that change it)."""
    return Path(shutil.copytree(captures[0], tmp_path / "scene", symlinks=True))


def tree(folder: Path) -> dict[str, str]:
    """Every entry under ``folder`` → its content hash (files), link target (links) or "dir"."""
    found = {}
    for path in sorted(folder.rglob("*")):
        name = str(path.relative_to(folder))
        if path.is_symlink():
            found[name] = "link:" + os.readlink(path)
        elif path.is_dir():
            found[name] = "dir"
        else:
            found[name] = hashlib.sha256(path.read_bytes()).hexdigest()
    return found


def convert(capsys, *args) -> tuple[int, str]:
    code = main(["convert", *map(str, args)])
    return code, capsys.readouterr().err


def frame_only(scene: Path, out: Path) -> dict:
    return pipeline.run_convert(scene, out, stages=("frame",))


def test_converting_into_another_capture_changes_none_of_its_files(captures, capsys):
    a, b = captures
    before = tree(b)
    code, err = convert(capsys, a, "--out", b)
    assert code == 2 and err.count("\n") == 1
    assert err.startswith(f"phirie: error: --out {b}: holds a capture's inputs (point_cloud.ply, transforms.json, ")
    assert "nothing was written" in err
    assert tree(b) == before


def test_an_output_folder_inside_the_scene_is_refused(captures, capsys):
    a, _ = captures
    before = tree(a)
    code, err = convert(capsys, a, "--out", a / "out")
    assert code == 2 and f"inside the scene folder {a}" in err and err.count("\n") == 1
    assert tree(a) == before


def test_an_output_file_never_replaces_a_file_no_run_wrote(captures, tmp_path, capsys):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "scene.xml").write_text("<mujoco>my own</mujoco>")
    code, err = convert(capsys, captures[0], "--out", out)
    assert code == 2 and "holds files a run would replace (scene.xml)" in err
    assert (out / "scene.xml").read_text() == "<mujoco>my own</mujoco>" and sorted(os.listdir(out)) == ["scene.xml"]


def test_an_input_inside_the_output_folder_is_refused(captures, tmp_path, capsys):
    out = tmp_path / "out"
    frame_only(captures[0], out)
    shutil.copy(captures[0] / "point_cloud.ply", out / "mine.ply")
    before = tree(out)
    code, err = convert(capsys, captures[0], "--out", out, "--gaussians", out / "mine.ply")
    assert code == 2 and f"holds the Gaussians {out / 'mine.ply'}" in err
    assert tree(out) == before


def _other_manifest(out: Path) -> None:
    out.mkdir()
    (out / "manifest.json").write_text('{"tool": "someone else\'s"}')


def _link_at_a_written_name(out: Path) -> None:
    out.mkdir()
    (out / "manifest.json").write_text('{"schema": "phirie/1"}')
    (out.parent / "elsewhere").mkdir()
    os.symlink(out.parent / "elsewhere", out / "objects")


def _read_only(out: Path) -> None:
    out.mkdir()
    out.chmod(0o555)


# (case, how the folder is made from (out, scene copy, other capture) → the --out to give, refused?)
# A read-only folder is refused, except for root (CI), who can write into it: either way no input changes.
CASES = {
    "new": (lambda out, a, b: out, False),
    "new, nested": (lambda out, a, b: out / "x" / "y", False),
    "earlier output": (lambda out, a, b: (frame_only(a, out), out)[1], False),
    "unrelated files": (lambda out, a, b: (out.mkdir(), (out / "notes.txt").write_text("mine"), out)[2], False),
    "another capture": (lambda out, a, b: b, True),
    "inside the scene": (lambda out, a, b: a / "out", True),
    "holds the scene": (lambda out, a, b: a.parent, True),
    "the scene itself": (lambda out, a, b: a, True),
    "a file": (lambda out, a, b: (out.write_text("x"), out)[1], True),
    "under a file": (lambda out, a, b: (out.write_text("x"), out / "sub")[1], True),
    "someone else's manifest": (lambda out, a, b: (_other_manifest(out), out)[1], True),
    "a link at a written name": (lambda out, a, b: (_link_at_a_written_name(out), out)[1], True),
    "read-only": (lambda out, a, b: (_read_only(out), out)[1], os.geteuid() != 0),
}


@pytest.mark.parametrize("case", list(CASES))
def test_no_input_file_changes_whatever_the_output_folder(case, captures, tmp_path):
    work = tmp_path / "work"
    a = Path(shutil.copytree(captures[0], work / "a"))
    b = Path(shutil.copytree(captures[1], tmp_path / "b"))
    make, refused = CASES[case]
    out = make(tmp_path / "out", a, b)
    inputs = {"a": tree(a), "b": tree(b)}
    before = tree(out) if out.is_dir() else None
    try:
        if refused:
            with pytest.raises(OptionError, match="^--out "):
                frame_only(a, out)
            assert (tree(out) if out.is_dir() else None) == before
        else:
            manifest = frame_only(a, out)
            assert manifest["stages"]["frame"] == "complete" and (out / layout.CAMERAS).is_file()
            assert not (out / layout.LOCK).exists()
    finally:
        if out.exists():
            out.chmod(0o755)
    assert {"a": tree(a), "b": tree(b)} == inputs


# --- links out of the scene ---------------------------------------------------------------------------


def _link_an_image_outside(scene: Path, tmp_path: Path) -> Path:
    outside = tmp_path / "outside.png"
    image = scene / "images" / "0003.png"
    shutil.move(image, outside)
    os.symlink(outside, image)
    return outside


@pytest.mark.parametrize("layout_name", ["colmap", "nerfstudio"])
def test_an_image_linked_outside_the_scene_needs_allow_outside_paths(layout_name, scene, tmp_path):
    if layout_name == "nerfstudio":
        shutil.rmtree(scene / "sparse")
    outside = _link_an_image_outside(scene, tmp_path)
    with pytest.raises(SceneInputError, match=f"0003.png' is a symbolic link to {outside}, outside {scene} ") as err:
        load_scene(scene)
    assert "--allow-outside-paths reads it anyway" in str(err.value)
    with outside_paths_allowed():
        assert load_scene(scene).layout == layout_name
    inside = scene / "images" / "0004.png"   # a link that stays in the scene is the scene's own choice
    shutil.move(inside, scene / "kept.png")
    os.symlink(scene / "kept.png", inside)
    os.unlink(scene / "images" / "0003.png")
    shutil.move(outside, scene / "images" / "0003.png")
    assert load_scene(scene).layout == layout_name


def test_a_mask_linked_outside_the_scene_is_refused(scene, tmp_path):
    mask = scene / "masks" / "0003.png"
    shutil.move(mask, tmp_path / "mask.png")
    os.symlink(tmp_path / "mask.png", mask)
    with pytest.raises(SceneInputError, match="mask: 'masks/0003.png' is a symbolic link to"):
        load_scene(scene)


# --- one run at a time, and a killed run ------------------------------------------------------------


def start_conversion(scene: Path, out: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "phirie_jax.cli", "convert", str(scene), "--out", str(out), *CHEAP],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)


def holder_pid(out: Path) -> int | None:
    try:
        return json.loads((out / layout.LOCK).read_text())["pid"]
    except (OSError, ValueError, KeyError):
        return None


def stage_status(out: Path) -> dict:
    try:
        return json.loads((out / layout.MANIFEST).read_text()).get("stages") or {}
    except (OSError, ValueError):
        return {}


def test_a_second_conversion_into_the_same_folder_is_refused_and_the_first_completes(captures, tmp_path, capsys):
    out = tmp_path / "out"
    first = start_conversion(captures[0], out)
    try:
        assert wait_for(lambda: holder_pid(out) == first.pid, 60), first.stderr.read1().decode()
        code, err = convert(capsys, captures[0], "--out", out, *CHEAP)
        assert code == 2 and err.count("\n") == 1
        assert err.startswith(f"phirie: error: --out {out}: in use by process {first.pid} on ")
        assert "wait for it to finish or stop it" in err
        assert first.wait(CONVERSION_SECONDS) == 0, first.stderr.read().decode()
    finally:
        kill_quietly(first.pid)
    assert set(stage_status(out).values()) == {"complete"} and not (out / layout.LOCK).exists()


def test_a_killed_conversion_is_not_taken_for_a_converted_one(captures, tmp_path, capsys):
    out = tmp_path / "out"
    run = start_conversion(captures[0], out)
    try:
        assert wait_for(lambda: stage_status(out).get("objects") == "running", 120), run.stderr.read1().decode()
    finally:
        os.killpg(run.pid, signal.SIGKILL)
        run.wait()
    assert (out / layout.LOCK).exists()       # the killed run could not remove it
    before = (out / layout.MANIFEST).read_bytes()

    assert main(["info", str(out), "--json"]) == 0
    facts = json.loads(capsys.readouterr().out)
    assert facts["state"] == "incomplete: the objects stage did not finish (the run was killed, or is still running)"
    assert facts["stages"] == {"frame": "complete", "observe": "complete", "objects": "running",
                               "physics": "pending", "background": "pending"}
    assert facts["files"][layout.SCENE_MJCF] == "not written"
    assert main(["info", str(out)]) == 0
    assert "(incomplete: the objects stage did not finish" in capsys.readouterr().out

    assert main(["droptest", str(out)]) == 2
    note, error = capsys.readouterr().err.splitlines()
    assert f"took over the lock of process {run.pid} on " in note and note.endswith("which is no longer running")
    assert error == (f"phirie: error: {out / layout.MANIFEST}: stages: the objects stage did not finish (the run was "
                     "killed, or is still running) (expected a complete conversion for the drop tests: run phirie "
                     "convert again)")
    assert (out / layout.MANIFEST).read_bytes() == before and not (out / layout.LOCK).exists()


def test_a_stale_lock_file_is_taken_over(captures, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / layout.LOCK).write_text(json.dumps({"pid": 2 ** 22 + 7, "host": "elsewhere", "command": "phirie convert"}))
    frame_only(captures[0], out)
    assert f"took over the lock of process {2 ** 22 + 7} on elsewhere (phirie convert)" in capsys.readouterr().err
    assert not (out / layout.LOCK).exists()


# --- messages -------------------------------------------------------------------------------------------


def test_known_size_of_an_instance_the_masks_lack_is_refused_before_any_work(captures, tmp_path, capsys):
    code, err = convert(capsys, captures[0], "--out", tmp_path / "out", "--known-size", "99=0.1")
    assert code == 2 and err == (f"phirie: error: {captures[0] / 'masks'}: --known-size: no instance 99 in the mask "
                                 "files (their instance ids: 1, 2, 3)\n")
    assert not (tmp_path / "out").exists()


def test_known_size_with_automatic_masks_says_when_it_is_checked(captures, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(pipeline, "STAGES", {"frame": pipeline.Stage(lambda run: run)})
    pipeline.run_convert(captures[0], tmp_path / "out", masks="auto", frame=pipeline.FrameConfig(known_size="99=0.1"))
    assert ("phirie: note: --known-size 99=0.1: instance 99 is checked after observation"
            in capsys.readouterr().err)


def test_synth_never_writes_over_a_capture(captures, tmp_path, capsys):
    """``phirie synth OUT`` writes a new, an empty or its own earlier folder, never another."""
    other = tmp_path / "other"
    other.mkdir()
    (other / "transforms.json").write_text("{}")
    assert main(["synth", str(other), "--preset", "tiny"]) == 2
    assert capsys.readouterr().err == (f"phirie: error: {other}: holds files (transforms.json) and is not an earlier "
                                       "output of this command (expected a new or empty folder); nothing was written\n")
    assert sorted(os.listdir(other)) == ["transforms.json"] and (other / "transforms.json").read_text() == "{}"
