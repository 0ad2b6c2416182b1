"""Do two compilations of the batched worlds' MJX step give the same worlds? One JSON object.

One compiled program is deterministic run to run; whether two compilations of it agree depends
on the compiler (on a GPU, XLA's autotuner times candidate kernels per fusion and keeps the
fastest). ``run`` steps ``--worlds`` worlds of a converted scene, each thrown as in
``bench_scaling`` (every velocity ~ N(0, ``--throw``), seeded), for ``--calls`` calls of
``--steps`` steps in a fresh process and compilation (no compilation cache), prints its timing
and saves the final qpos; ``compare`` counts the worlds two saved runs agree on bit for bit:

    python -m experiments.compile_determinism run --scene out/scaling/convert --out /tmp/a.npy
    python -m experiments.compile_determinism run --scene out/scaling/convert --out /tmp/b.npy
    python -m experiments.compile_determinism compare /tmp/a.npy /tmp/b.npy

With ``XLA_FLAGS=--xla_gpu_autotune_level=0`` for both runs, XLA keeps its default kernel for
each fusion instead of the fastest it measured (``docs/scaling.md``).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from experiments.report import emit


def run(args) -> dict:
    import jax

    jax.config.update("jax_enable_compilation_cache", False)   # a compilation of its own

    from experiments.bench_scaling import throws
    from experiments.timing import timed_steps
    from phirie_jax.interact.batched import BatchedEnvironment
    from phirie_jax.interact.environment import Environment
    from phirie_jax.io.atomic import atomic_write

    env = Environment.load(args.scene)
    batch = BatchedEnvironment(env, args.worlds, devices=1)
    batch.set_velocities(throws(env, args.worlds, args.throw, args.seed))
    first, call_s = timed_steps(batch, args.steps, args.calls - 1)
    with atomic_write(args.out) as f:
        np.save(f, np.asarray(batch.data.qpos))
    return {"device": jax.devices()[0].device_kind, "jax": jax.__version__,
            "xla_flags": os.environ.get("XLA_FLAGS", ""), "worlds": args.worlds, "steps": args.steps * args.calls,
            "compile_s": round(first - call_s, 2),
            "ms_per_step": round(1e3 * call_s / args.steps, 3), "qpos": str(args.out)}


def compare(first: Path, second: Path) -> dict:
    a, b = np.load(first), np.load(second)
    if a.shape != b.shape:
        raise SystemExit(f"compare: {first} holds qpos of shape {a.shape}, {second} {b.shape} (expected the same)")
    return {"runs": [str(first), str(second)], "worlds": int(a.shape[0]),
            "worlds_equal": int(np.sum(np.all(a == b, axis=1))),
            "max_abs_qpos_difference": float(np.max(np.abs(a.astype(np.float64) - b), initial=0.0))}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    stepping = commands.add_parser("run", help="step the worlds in a fresh compilation and save their qpos")
    stepping.add_argument("--scene", type=Path, required=True, help="a phirie convert output folder")
    stepping.add_argument("--out", type=Path, required=True, help="the .npy the final qpos (worlds × nq) goes to")
    stepping.add_argument("--worlds", type=int, default=512)
    stepping.add_argument("--steps", type=int, default=240, help="steps per call")
    stepping.add_argument("--calls", type=int, default=3)
    stepping.add_argument("--throw", type=float, default=0.3)
    stepping.add_argument("--seed", type=int, default=0)
    comparing = commands.add_parser("compare", help="count the worlds two runs agree on")
    comparing.add_argument("first", type=Path)
    comparing.add_argument("second", type=Path)
    args = parser.parse_args(argv)
    if args.command == "run" and args.calls < 2:
        parser.error("--calls: at least 2 (the first compiles)")
    emit(run(args) if args.command == "run" else compare(args.first, args.second), None)


if __name__ == "__main__":
    sys.exit(main())
