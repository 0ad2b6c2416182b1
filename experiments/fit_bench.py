"""Fitted-synthetic benchmark: how long a 3DGS fit of a synthetic scene's images takes, and how well
it reproduces them (``phirie_jax.synthetic.fitted``); prints one JSON object.

    python -m experiments.fit_bench [--preset tiny] [--seed 0] [--steps N] [--out result.json]

Synthesizes the preset into a temporary folder (or fits ``--scene DIR``, a ``phirie synth`` folder
that is not fitted yet, without changing it), then fits. Times: ``compile_s`` = the first call of
each compiled step program (one per Gaussian bucket × intersection capacity) less one step's run
time; ``run_s`` = the rest of the loop (steps, densification on the host); ``steps_per_s`` =
1 / the median step of an already compiled program. Also the final train PSNR (mean over the
views), the Gaussian counts and the buckets.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

from experiments.report import emit


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="tiny", choices=["tiny", "default", "large"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=None, help="Adam steps (default: the preset's, FIT_PRESETS)")
    parser.add_argument("--scene", type=Path, default=None, help="a synthesized folder to fit instead")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()

    import jax

    from phirie_jax.synthetic import PRESETS, synthesize
    from phirie_jax.synthetic.fitted import fit_config_for, fit_gaussians, read_training_views

    config = fit_config_for(args.preset, args.steps)
    with tempfile.TemporaryDirectory() as tmp:
        scene_dir = args.scene
        synth_s = None
        if scene_dir is None:
            scene_dir = Path(tmp) / "scene"
            t0 = time.perf_counter()
            synthesize(scene_dir, preset=args.preset, seed=args.seed)
            synth_s = round(time.perf_counter() - t0, 3)
        images, cameras = read_training_views(scene_dir)
        t0 = time.perf_counter()
        result = fit_gaussians(images, cameras, config, seed=args.seed, background=PRESETS[args.preset].background_rgb)
        total_s = time.perf_counter() - t0
    r = result.record
    out = {
        "preset": args.preset, "seed": args.seed, "scene": str(args.scene) if args.scene else None,
        "views": len(cameras), "image": [cameras[0].width, cameras[0].height],
        "backend": jax.default_backend(), "device": str(jax.devices()[0]),
        "machine": {"platform": platform.platform(), "processor": platform.processor(), "cpus": os.cpu_count(),
                    "load_average_at_end": os.getloadavg()},
        "steps": r["steps"], "compile_s": r["compile_s"], "run_s": r["run_s"],
        "steps_per_s": round(1.0 / r["step_s_median"], 3) if r["step_s_median"] else None,
        "fit_total_s": round(total_s, 3), "synthesize_s": synth_s, "programs": r["programs"],
        "train_psnr": r["train_psnr"], "train_psnr_min": min(r["train_psnr_per_view"]),
        "gaussians_initial": r["initial_gaussians"], "gaussians": r["gaussians"], "buckets": r["buckets"],
        "capacity": r["capacity"], "capacity_retries": r["capacity_retries"], "densify": r["densify"],
        "config": r["config"],
    }
    emit(out, args.out)


if __name__ == "__main__":
    main()
