"""Fitted synthetic scenes made on a GPU host and installed here: the ``default`` preset's fit
(``FIT_PRESETS["default"]``, 3600 Adam steps) takes an hour or more on two CPU cores and about
a minute on a GPU, so the evaluations' fitted scenes are fitted there and reproduced here by
their seed.

    # on the GPU host: synthesize and fit; one .npz per seed (the fitted set and gt/fit.json)
    python -m experiments.fit_scenes fit --preset default --seeds 2001 2002 --out DIR
    # here: synthesize the same preset and seed, then make the fitted set its capture
    python -m experiments.fit_scenes install DIR/fit_default_2001.npz --dest /tmp/phirie_scenes/eval{seed}_fitted

``fit`` prints one JSON object per run (times, train PSNR, Gaussian counts); ``--budget-s`` stops
starting new seeds once that much wall time has passed. ``install`` synthesizes the folder where it
is missing (the same files on any backend up to float rounding in the images) and calls
``install_fit``; ``gt/fit.json`` then says where the fit ran (``backend``, ``device``).
"""

from __future__ import annotations

import argparse
import io
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from experiments.report import emit

FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh")


def export_fit(path: Path, result) -> None:
    """The fitted set's arrays and its record in one compressed .npz (written then renamed)."""
    from phirie_jax.io.atomic import write_bytes

    buf = io.BytesIO()
    np.savez_compressed(buf, record=np.array(json.dumps(result.record)),
                        **{k: getattr(result.gaussians, k) for k in FIELDS})
    write_bytes(path, buf.getvalue())


def read_fit(path: Path):
    from phirie_jax.synthetic.fitted import FitResult
    from phirie_jax.types import GaussianSplatData

    with np.load(path) as z:
        missing = [k for k in FIELDS + ("record",) if k not in z.files]
        if missing:
            raise ValueError(f"{path}: not a fit export (missing {', '.join(missing)})")
        data = GaussianSplatData(**{k: np.asarray(z[k], np.float32) for k in FIELDS})
        return FitResult(data, json.loads(str(z["record"])))


def fit(args) -> None:
    from phirie_jax.synthetic.fitted import fit_config_for, synthesize_fitted

    config = fit_config_for(args.preset, args.steps)
    args.out.mkdir(parents=True, exist_ok=True)
    start, runs = time.perf_counter(), []
    for seed in args.seeds:
        if runs and time.perf_counter() - start > args.budget_s:
            print(f"budget of {args.budget_s:.0f} s spent: seeds from {seed} on not fitted", flush=True)
            break
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            _, result = synthesize_fitted(Path(tmp) / "scene", args.preset, seed, config)
            total = time.perf_counter() - t0
        export_fit(args.out / f"fit_{args.preset}_{seed}.npz", result)
        r = result.record
        runs.append({"seed": seed, "synthesize_and_fit_s": round(total, 2), "fit_wall_s": r["wall_s"],
                     "compile_s": r["compile_s"], "run_s": r["run_s"],
                     "steps_per_s": round(1.0 / r["step_s_median"], 2) if r["step_s_median"] else None,
                     "train_psnr": r["train_psnr"], "train_psnr_min": min(r["train_psnr_per_view"]),
                     "gaussians": r["gaussians"], "buckets": r["buckets"], "device": r["device"]})
        print(json.dumps(runs[-1]), flush=True)
    emit({"preset": args.preset, "steps": config.steps, "runs": runs}, args.out / f"fit_{args.preset}.json")


def install(args) -> None:
    from phirie_jax.synthetic.fitted import ensure_synthesized, install_fit

    for path in args.fits:
        result = read_fit(path)
        seed, preset = int(result.record["seed"]), path.stem.split("_")[1]
        dest = Path(str(args.dest).format(seed=seed))
        if (dest / "gt" / "fit.json").exists():
            print(f"{dest}: already fitted, left as it is", flush=True)
            continue
        ensure_synthesized(dest, preset, seed)
        install_fit(dest, result)
        print(f"{dest}: {result.gaussians.num:,} fitted Gaussians from {path} "
              f"(train PSNR {result.record['train_psnr']:.2f} dB on {result.record['device']})", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    f = sub.add_parser("fit", help="synthesize and fit, one .npz per seed")
    f.add_argument("--preset", default="default", choices=["tiny", "default", "large"])
    f.add_argument("--seeds", type=int, nargs="+", required=True)
    f.add_argument("--steps", type=int, default=None, help="Adam steps (default: the preset's)")
    f.add_argument("--budget-s", type=float, default=float("inf"))
    f.add_argument("--out", type=Path, required=True)
    i = sub.add_parser("install", help="synthesize here and make an exported fit the capture")
    i.add_argument("fits", type=Path, nargs="+")
    i.add_argument("--dest", required=True, help="folder per fit; {seed} is replaced by its seed")
    args = parser.parse_args()
    fit(args) if args.command == "fit" else install(args)


if __name__ == "__main__":
    main()
