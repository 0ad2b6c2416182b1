"""``phirie capture``'s stages in order, in a working folder beside the target, resumable.

The work happens in ``.NAME.capture/`` beside the target folder ``NAME``: the pictures
(``frames/``), the structure from motion (``sfm/``), the training's checkpoint and finally the
scene (``scene/``), which is renamed to the target at the end (an earlier capture there is
replaced); then the working folder is removed. So the target never holds a partial scene.

Bad input (too few or unreadable pictures, too few registered) removes the working folder and
raises ``SceneInputError``. Anything else, a kill included, leaves it: ``resume=True`` then
skips the stages already done (``progress.json`` records them) and continues the training from
its last checkpoint, provided the source and the settings are those of the interrupted run.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import time
from pathlib import Path

import numpy as np

from phirie_jax.capture.config import CaptureConfig, TrainConfig
from phirie_jax.capture.frames import Frames, prepare_frames
from phirie_jax.capture.scene import CAPTURE_RECORD, held_out, training_views, write_record, write_scene
from phirie_jax.capture.sfm import load_sfm, run_sfm
from phirie_jax.errors import SceneInputError
from phirie_jax.geometry import sigmoid
from phirie_jax.io.atomic import write_text
from phirie_jax.io.output_folder import check_scene_target
from phirie_jax.progress import task

PROGRESS = "progress.json"
TRAINERS = ("jax", "gsplat")


def work_folder(out: Path) -> Path:
    """Where a capture into ``out`` works: ``.NAME.capture`` beside it."""
    out = Path(out).absolute()
    return out.parent / f".{out.name}.capture"


def _settings(source: Path, config: CaptureConfig, trainer: str) -> dict:
    return {"source": str(Path(source).absolute()), "trainer": trainer, "config": dataclasses.asdict(config)}


def _progress(work: Path, source: Path, config: CaptureConfig, trainer: str, resume: bool) -> dict:
    """The working folder's record of what is done (a fresh one unless resuming the same capture)."""
    settings = _settings(source, config, trainer)
    path = work / PROGRESS
    if resume and path.is_file():
        done = json.loads(path.read_text(encoding="utf-8"))
        if done.get("settings") != json.loads(json.dumps(settings)):
            raise SceneInputError(path, "settings", "the interrupted capture had another source, trainer or settings "
                                  "(expected the same command to resume; run without --resume to start again)")
        return {**done, "resumed": True}
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    return {"settings": settings}


def _save(work: Path, done: dict) -> None:
    write_text(work / PROGRESS, json.dumps(done, indent=2))


def _install(stage: Path, out: Path) -> None:
    """Rename the finished scene to ``out``, replacing an earlier capture's folder there."""
    old = None
    if out.exists():
        old = out.parent / f".{out.name}.replaced"
        if old.exists():
            shutil.rmtree(old)
        out.rename(old)
    stage.rename(out)
    if old is not None:
        shutil.rmtree(old)


def run_capture(source: str | Path, out: str | Path, config: CaptureConfig | None = None, *,
                resume: bool = False, trainer: str = "jax") -> dict:
    """Photos or a video at ``source`` → the scene folder ``out`` (module docstring, ``scene``).
    config: default ``CaptureConfig()``; trainer: "jax" (the project's renderer) or "gsplat"
    (gsplat, when installed). Returns the capture record (what ``capture.json`` holds)."""
    source, out, config = Path(source), Path(out), config or CaptureConfig()
    if trainer not in TRAINERS:
        raise ValueError(f"trainer {trainer!r} (expected one of {TRAINERS})")
    check_scene_target(out, CAPTURE_RECORD)
    if not source.exists():
        raise SceneInputError(source, None, "not found (expected a folder of photos or a video file)")
    if trainer == "gsplat":
        import os

        from phirie_jax.capture.gsplat_train import require_gsplat

        # JAX scores gsplat's Gaussians in this process, beside PyTorch: it must not take 75 % of the GPU
        os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
        require_gsplat()
    work = work_folder(out)
    t_start = time.perf_counter()
    done = _progress(work, source, config, trainer, resume)
    try:
        return _stages(source, out, config, trainer, work, done, resume, t_start)
    except SceneInputError:
        shutil.rmtree(work, ignore_errors=True)  # bad input: nothing to resume
        raise


def _stages(source: Path, out: Path, config: CaptureConfig, trainer: str, work: Path, done: dict, resume: bool,
            t_start: float) -> dict:
    timings = done.setdefault("timings", {})
    if "frames" in done:
        frames = Frames.from_json(done["frames"])
    else:
        t = time.perf_counter()
        frames = prepare_frames(source, config.frames, work / "frames")
        done["frames"], timings["frames_s"] = frames.as_json(), round(time.perf_counter() - t, 3)
        _save(work, done)
    if "sfm" in done:
        sfm = load_sfm(work / "sfm", done["sfm"])
    else:
        t = time.perf_counter()
        sfm = run_sfm(frames, config.sfm, work / "sfm")
        done["sfm"], timings["sfm_s"] = sfm.record, round(time.perf_counter() - t, 3)
        _save(work, done)

    cameras, images = training_views(sfm.cameras)
    holdout = held_out(len(cameras), config.train.holdout_every)
    if holdout.all():
        raise SceneInputError(source, "pictures", f"{len(cameras)} registered, all held out for scoring "
                              "(expected more: set --config.train.holdout-every 0 to train on all)")
    train = [i for i in range(len(cameras)) if not holdout[i]]
    test = [i for i in range(len(cameras)) if holdout[i]]
    t = time.perf_counter()
    if trainer == "gsplat":
        from phirie_jax.capture.gsplat_train import train_with_gsplat
        from phirie_jax.capture.train import camera_extent

        gaussians, training = train_with_gsplat(cameras, images, train, test, sfm.points, sfm.colours, config.train,
                                                camera_extent(cameras))
        ours = score_held_out(gaussians, cameras, images, test, config.train.background)
        training["held_out_psnr_phirie_renderer"] = ours and ours["held_out_psnr"]
    else:
        gaussians, training = train_with_jax(cameras, images, train, test, sfm.points, sfm.colours, config.train,
                                             work / "checkpoint.npz", resume)
    timings["train_s"] = round(time.perf_counter() - t, 3)

    t = time.perf_counter()
    kept = gaussians.subset(sigmoid(gaussians.opacity_logits) >= config.train.min_opacity)
    stage = work / "scene"
    if stage.exists():
        shutil.rmtree(stage)
    write_scene(stage, cameras, images, sfm.points, sfm.colours, kept)
    timings["write_s"] = round(time.perf_counter() - t, 3)
    timings["this_run_s"] = round(time.perf_counter() - t_start, 3)  # a resumed run: from its start
    record = {"source": str(source.absolute()), "trainer": trainer, "resumed": resume and "resumed" in done,
              "frames": frames.record, "sfm": sfm.record, "training": {**training, "gaussians_written": kept.num},
              "timings": timings}
    write_record(stage, record)
    _install(stage, out)
    shutil.rmtree(work, ignore_errors=True)
    return record


def train_with_jax(cameras, images, train: list[int], test: list[int], points, colours, tc: TrainConfig,
                   checkpoint: Path | None = None, resume: bool = False):
    """Train with the project's renderer from the SfM points (P, 3) and colours (P, 3) uint8, on
    the views ``train`` of cameras and images, scoring ``test``; checkpoints to ``checkpoint``.
    Returns the Gaussians and the training record (``train_with_gsplat``'s counterpart)."""
    from phirie_jax.capture.train import (
        Views,
        camera_extent,
        init_from_points,
        peak_device_memory_mb,
        train_gaussians,
        views_psnr,
    )

    rng = np.random.default_rng(tc.seed)
    extent = camera_extent(cameras)
    init = init_from_points(points, np.asarray(colours, np.float64) / 255.0, tc, rng)
    views = Views.of([images[i] for i in train], [cameras[i] for i in train])
    with task(f"training {tc.steps} steps on {len(train)} views", tc.steps) as advance:
        shown = [0]

        def on_step(step: int, loss: float, count: int) -> None:
            advance(step - shown[0])
            shown[0] = step
            if step % 100 == 0 or step == tc.steps:
                advance.update(f"training: step {step}/{tc.steps}, loss {loss:.4f}, {count:,} Gaussians")

        trained = train_gaussians(init, views, extent, tc, rng, tc.background, checkpoint=checkpoint,
                                  resume=resume, on_step=on_step, donate=True)
    peak = peak_device_memory_mb()
    with task("scoring the held-out views"):
        train_psnr = views_psnr(trained.gaussians, views, tc.background, trained.raster, clip=True)
        test_psnr = score_held_out(trained.gaussians, cameras, images, test, tc.background, trained.raster)
    record = {**trained.record, "extent": round(extent, 6), "views_trained": len(train),
              "held_out": [cameras[i].name for i in test], **(test_psnr or {"held_out_psnr": None}),
              "train_psnr": round(float(np.mean(train_psnr)), 3), "peak_gpu_mb": peak,
              "config": dataclasses.asdict(tc)}
    return trained.gaussians, record


def score_held_out(gaussians, cameras, images, test: list[int], background, raster=None) -> dict | None:
    """Held-out PSNR of ``gaussians`` rendered by the project's renderer (clamped to [0, 1])."""
    from kernels.raster import RasterConfig
    from phirie_jax.capture.train import Views, views_psnr

    if not test:
        return None
    views = Views.of([images[i] for i in test], [cameras[i] for i in test])
    psnr = views_psnr(gaussians, views, background, raster or RasterConfig(), clip=True)
    return {"held_out_psnr": round(float(np.mean(psnr)), 3), "held_out_psnr_per_view": np.round(psnr, 3).tolist()}
