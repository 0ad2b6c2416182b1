"""``phirie convert`` checks its inputs before it creates or touches the output folder (one line
each, no traceback), leaves no partial output after an input error, and starts by removing the
temporaries a killed earlier run left where the stages write. The scene is a hand-made
two-camera nerfstudio folder; the stages themselves are replaced where a test needs them run."""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from phirie_jax import pipeline
from phirie_jax.cli import main
from phirie_jax.errors import SceneInputError, StageError
from phirie_jax.io.camera import intrinsics_matrix
from phirie_jax.io.ply import write_gaussian_ply
from phirie_jax.io.transforms_json import write_transforms_json
from phirie_jax.types import Camera, GaussianSplatData

WIDTH, HEIGHT = 16, 12


def write_scene(root: Path) -> Path:
    """Two cameras (transforms.json, images/) and a Gaussian PLY of 20 splats."""
    cameras = [Camera(f"{i}.png", intrinsics_matrix(20.0, 20.0, WIDTH / 2, HEIGHT / 2),
                      np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2.0 + i], [0, 0, 0, 1]], float),
                      WIDTH, HEIGHT) for i in range(2)]
    write_transforms_json(root / "transforms.json", cameras)
    (root / "images").mkdir()
    for cam in cameras:
        assert cv2.imwrite(str(root / "images" / cam.name), np.full((HEIGHT, WIDTH, 3), 90, np.uint8))
    n = 20
    write_gaussian_ply(root / "point_cloud.ply", GaussianSplatData(
        means=np.random.default_rng(0).uniform(-0.2, 0.2, (n, 3)).astype(np.float32),
        quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)), log_scales=np.full((n, 3), -4, np.float32),
        opacity_logits=np.zeros(n, np.float32), sh=np.zeros((n, 1, 3), np.float32)))
    return root


@pytest.fixture
def scene(tmp_path) -> Path:
    return write_scene(tmp_path / "scene")


def convert(capsys, *args) -> tuple[int, str]:
    code = main(["convert", *map(str, args)])
    return code, capsys.readouterr().err


def test_an_existing_file_as_out_is_one_line(tmp_path, capsys):
    (tmp_path / "afile").write_text("keep")
    code, err = convert(capsys, tmp_path, "--out", tmp_path / "afile")
    assert code == 2 and err == (f"phirie: error: --out {tmp_path / 'afile'}: is a file (expected a folder: "
                                 "a new one or an earlier run's output)\n")
    code, err = convert(capsys, tmp_path, "--out", tmp_path / "afile" / "sub")
    assert code == 2 and err.startswith(f"phirie: error: --out {tmp_path / 'afile' / 'sub'}: {tmp_path / 'afile'} "
                                        "is a file")
    assert (tmp_path / "afile").read_text() == "keep"


def test_the_scene_folder_is_not_an_output_folder(scene, capsys):
    before = (scene / "transforms.json").read_bytes()
    code, err = convert(capsys, scene, "--out", scene)
    assert code == 2 and "the scene folder itself" in err and err.count("\n") == 1
    assert (scene / "transforms.json").read_bytes() == before and not (scene / "manifest.json").exists()


def test_a_lone_ply_says_what_to_pass_instead(scene, tmp_path, capsys):
    code, err = convert(capsys, scene / "point_cloud.ply", "--out", tmp_path / "out")
    assert code == 2 and err == (f"phirie: error: {scene / 'point_cloud.ply'}: a Gaussian PLY alone has no cameras "
                                 f"(expected its scene folder, {scene}, which holds it and the cameras)\n")
    other = scene / "other.ply"
    other.write_bytes((scene / "point_cloud.ply").read_bytes())
    _, err = convert(capsys, other, "--out", tmp_path / "out")
    assert f"expected its scene folder, {scene}, which holds the cameras, and --gaussians {other}" in err
    elsewhere = tmp_path / "elsewhere.ply"
    elsewhere.write_bytes(other.read_bytes())
    _, err = convert(capsys, elsewhere, "--out", tmp_path / "out")
    assert f"expected a scene folder with cameras and images, and --gaussians {elsewhere}" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("args, message", [
    (["--masks", "MISSING"], "--masks: folder not found"),
    (["--masks", "files"], "--masks files: no masks/ folder"),
    (["--config.observe.surface-source", "mesh"], "surface: no scan mesh"),
    (["--config.background.targets.external", "MISSING"], "targets: not a folder"),
], ids=["masks-folder", "masks-files", "surface-mesh", "external-targets"])
def test_an_input_error_leaves_the_output_folder_untouched(scene, tmp_path, capsys, args, message):
    args = [str(tmp_path / "missing") if a == "MISSING" else a for a in args]
    code, err = convert(capsys, scene, "--out", tmp_path / "new" / "out", *args)
    assert code == 2 and message in err and err.count("\n") == 1
    assert not (tmp_path / "new").exists()


def test_no_cameras_is_found_before_the_output_folder(tmp_path, capsys):
    (tmp_path / "scene").mkdir()
    write_gaussian_ply(tmp_path / "scene" / "point_cloud.ply", GaussianSplatData(
        means=np.zeros((1, 3), np.float32), quats=np.float32([[1, 0, 0, 0]]), log_scales=np.zeros((1, 3), np.float32),
        opacity_logits=np.zeros(1, np.float32), sh=np.zeros((1, 1, 3), np.float32)))
    code, err = convert(capsys, tmp_path / "scene", "--out", tmp_path / "out")
    assert code == 2 and "cameras: none found" in err and not (tmp_path / "out").exists()


def failing_frame(run):
    raise SceneInputError(run.capture.root, "scale", "cannot be estimated (a test)")


def test_an_input_error_a_stage_finds_removes_the_folder_this_run_created(scene, tmp_path, monkeypatch):
    monkeypatch.setattr(pipeline, "STAGES", {"frame": pipeline.Stage(failing_frame)})
    with pytest.raises(SceneInputError, match="cannot be estimated"):
        pipeline.run_convert(scene, tmp_path / "new" / "out")
    assert not (tmp_path / "new").exists()
    existing = tmp_path / "existing"
    existing.mkdir()
    with pytest.raises(SceneInputError):
        pipeline.run_convert(scene, existing)
    failed = json.loads((existing / "manifest.json").read_text())["failed_stage"]  # an earlier output stays
    assert failed["stage"] == "frame" and "cannot be estimated" in failed["error"]


class Job:
    """Work started ahead of its stage: says when it ends and whether a failure ended it."""

    def __init__(self, log: list):
        self.log = log

    def __enter__(self):
        return self

    def __exit__(self, kind, err, trace):
        self.log.append("job cancelled" if kind is not None else "job ends")


def logging_table(log: list, again: tuple[str, ...] = (), failing: str | None = None) -> dict:
    """The stage table with each stage replaced by one that logs its name (and ``failing`` raising)."""
    def step(name):
        def run(run):
            log.append(name)
            if name == failing:
                raise RuntimeError(f"{name} failed (a test)")
            return run
        return run

    def start(run):
        log.append("start physics")
        return run, Job(log)

    table = {name: pipeline.Stage(step(name)) for name in pipeline.STAGES}
    table["physics"] = pipeline.Stage(step("physics"), needs=pipeline.STAGES["physics"].needs, start=start,
                                      again=lambda run: again)
    return table


@pytest.mark.parametrize("stages, again, expected", [
    (None, (), ["frame", "observe", "objects", "start physics", "background", "physics", "job ends"]),
    (None, ("background",),
     ["frame", "observe", "objects", "start physics", "background", "physics", "background", "job ends"]),
    (("background", "physics"), (), ["frame", "start physics", "background", "physics", "job ends"]),
    (("physics",), ("background",), ["frame", "physics"]),   # nothing to run beside it; no background to redo
    (("objects", "physics"), (), ["frame", "objects", "physics"]),
])
def test_the_stages_run_in_the_table_order_with_work_started_ahead(scene, tmp_path, monkeypatch, stages, again,
                                                                   expected):
    """The physics stage's collision starts once the frame and the objects are done and a stage is left
    to run beside it (the background); a stage it outdates runs again if this run ran it."""
    assert list(pipeline.STAGES) == ["frame", "observe", "objects", "background", "physics"]
    log = []
    monkeypatch.setattr(pipeline, "STAGES", logging_table(log, again))
    pipeline.run_convert(scene, tmp_path / "out", masks="auto", stages=stages)
    assert log == expected


def test_work_started_ahead_ends_when_a_stage_fails_before_it_is_taken(scene, tmp_path, monkeypatch):
    log = []
    monkeypatch.setattr(pipeline, "STAGES", logging_table(log, failing="background"))
    with pytest.raises(StageError, match="background failed"):
        pipeline.run_convert(scene, tmp_path / "out", masks="auto")
    assert log == ["frame", "observe", "objects", "start physics", "background", "job cancelled"]


STALE = [".manifest.json.k3j_x9q2.tmp", "observe/.instance_1.npz.a1b2c3d4.tmp", "objects/1/.mesh.obj.zzzzzzzz.tmp",
         "objects/1/collision/.part_00.obj.0a_b1c2d.tmp", "background/.x.abcdefgh.tmp",
         "background/targets/.0.png.qwertyui.tmp"]
KEPT = ["notes.tmp", ".notes.tmp", ".mesh.obj.ABCDEFGH.tmp", ".mesh.obj.abc.tmp", ".mesh.obj.abcdefgh.tmp.bak",
        "mine/.a.abcdefgh.tmp", "objects/1/collision/sub/.part_00.obj.abcdefgh.tmp", "objects/1/mesh.obj"]


def test_a_run_removes_the_temporaries_a_killed_run_left_and_nothing_else(scene, tmp_path, monkeypatch):
    monkeypatch.setattr(pipeline, "STAGES", {"frame": pipeline.Stage(lambda run: run)})
    out = tmp_path / "out"
    out.mkdir()
    (out / "manifest.json").write_text('{"schema": "phirie/1"}')   # the first file a run writes
    for name in STALE + KEPT:
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_text("x")
    (out / "elsewhere").mkdir()
    os.symlink(out / "elsewhere", out / ".link.abcdefgh.tmp")   # a link named like one is not one
    pipeline.run_convert(scene, out)
    assert [name for name in STALE if (out / name).exists()] == []
    assert [name for name in KEPT if not (out / name).exists()] == []
    assert (out / ".link.abcdefgh.tmp").is_symlink()


def test_images_outside_the_scene_folder_need_allow_outside_paths(scene, tmp_path, capsys):
    meta = json.loads((scene / "transforms.json").read_text())
    (scene / "images" / "0.png").rename(tmp_path / "0.png")
    meta["frames"][0]["file_path"] = "../0.png"
    (scene / "transforms.json").write_text(json.dumps(meta))
    code, err = convert(capsys, scene, "--out", tmp_path / "out")
    assert code == 2 and err == (f"phirie: error: {scene / 'transforms.json'}: frames[0]: file_path: '../0.png' is "
                                 f"outside {scene} (expected an image inside the scene folder; --allow-outside-paths "
                                 "reads it anyway)\n")
    assert not (tmp_path / "out").exists()
    assert main(["info", str(scene), "--json", "--allow-outside-paths"]) == 0
    assert json.loads(capsys.readouterr().out)["cameras"]["count"] == 2
