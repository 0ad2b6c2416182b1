"""``phirie capture INPUT --out SCENE_DIR``: the command line of ``phirie_jax.capture.run``."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Annotated, Literal

import tyro

from phirie_jax.capture.config import CaptureConfig
from phirie_jax.ranges import AT_LEAST_ONE, Range, check_option

DEFAULTS = CaptureConfig()


def capture(input: Annotated[Path, tyro.conf.Positional], out: Path, frames: int | None = None,
            steps: int | None = None, max_gaussians: int | None = None, resolution: int | None = None,
            resume: bool = False, trainer: Literal["jax", "gsplat"] = "jax",
            config: CaptureConfig = DEFAULTS) -> None:
    """Photos or a video → a scene folder that `phirie convert` reads: sharp frames, structure from
    motion (pycolmap: SIFT, matching, incremental mapping, undistortion to pinhole), 3DGS training
    (gsplat's schedule and densification, the project's renderer), every 8th picture held out and
    scored. Writes SCENE_DIR/{transforms.json, images/, sparse/0/, point_cloud.ply, capture.json};
    the work happens in .SCENE_DIR.capture/ beside it, so SCENE_DIR never holds a partial scene.

    Args:
        input: a folder of photos (JPEG, PNG, ...) or a video file (MP4, MOV, ...).
        out: the scene folder to write (new, empty, or an earlier capture's).
        frames: for a video, the number of frames to keep (the sharpest of each stretch; default 120).
        steps: training steps (default 7,000: minutes on a GPU; a CPU manages a few hundred on small pictures).
        max_gaussians: densification stops adding at this count (default 2,000,000).
        resolution: pictures are downscaled to this many pixels on their longer side (default 1600).
        resume: continue an interrupted capture into the same folder from where it stopped (its
            pictures, SfM and last training checkpoint are kept in .SCENE_DIR.capture/).
        trainer: jax (the project's renderer: Pallas on a GPU, plain JAX on a CPU) or gsplat
            (needs gsplat, PyTorch and a CUDA GPU: pip install 'phirie_jax[gsplat]').
        config: every stage's settings (--config.sfm.*, --config.train.*, --config.frames.*).
    """
    check_option("--frames", frames, Range(2))
    check_option("--steps", steps, AT_LEAST_ONE)
    check_option("--max-gaussians", max_gaussians, AT_LEAST_ONE)
    check_option("--resolution", resolution, Range(32))
    config = _with_options(config, frames, steps, max_gaussians, resolution)

    from phirie_jax.capture.run import run_capture
    from phirie_jax.progress import display_for, showing

    with showing(display_for()):
        record = run_capture(input, out, config, resume=resume, trainer=trainer)
    sfm, training = record["sfm"], record["training"]
    print(f"registered {sfm['registered']} of {sfm['pictures']} pictures (mean reprojection error "
          f"{sfm['mean_reprojection_error_px']:.2f} px, {sfm['points']:,} points)")
    held = training.get("held_out_psnr")
    memory = training.get("peak_gpu_mb")
    print(f"trained {training['steps']:,} steps with {record['trainer']}: {training['gaussians_written']:,} Gaussians"
          + (f", held-out PSNR {held:.2f} dB ({len(training['held_out'])} views)" if held is not None else "")
          + (f", peak GPU memory {memory:,.0f} MiB" if memory is not None else ""))
    print(f"wrote {out} in {record['timings']['this_run_s']:.0f} s (capture.json); next: phirie convert {out} --out ...")


def _with_options(config: CaptureConfig, frames, steps, max_gaussians, resolution) -> CaptureConfig:
    """``config`` with the plain options (when given) in their fields."""
    frame_changes = {k: v for k, v in (("frames", frames), ("resolution", resolution)) if v is not None}
    train_changes = {k: v for k, v in (("steps", steps), ("max_gaussians", max_gaussians)) if v is not None}
    return dataclasses.replace(config, frames=dataclasses.replace(config.frames, **frame_changes),
                               train=dataclasses.replace(config.train, **train_changes))
