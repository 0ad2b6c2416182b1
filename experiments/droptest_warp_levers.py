"""Levers of the MuJoCo Warp drop test at one candidate count, measured in one run beside the
sequential PyBullet loop and multi-threaded MuJoCo C (``mujoco.rollout``); prints one JSON object.

    python -m experiments.droptest_warp_levers --count 1024 --out experiments/results/droptest_warp_levers_h100.json

A kernel profile of one step (``kernel_profile``) says where the step's time goes. Each lever is
a ``warp_batch.prepare`` setting (the default turns the model's unused features off,
``warp_batch.UNUSED_FEATURES``): fewer solver iterations, the CG solver, protocol steps per
captured CUDA graph, CUDA-graph
conditionals for the solver's early termination (``Option.graph_conditional``), the experimental
``run_qacc_smooth = False`` (no unconstrained acceleration or mass-matrix factorisation before
the Newton solve), and the early exit through sleeping. Per lever: run time (median of
``--repeats``), its ratios to PyBullet and rollout, and its verdicts against MuJoCo C.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import numpy as np

from experiments.bench_droptest import agreement, bench_c, bench_pybullet, bench_rollout, bodies_for, pybullet_available
from experiments.report import emit
from phirie_jax.construct.physics import warp_batch
from phirie_jax.construct.physics.config import DropTestConfig
from phirie_jax.construct.physics.droptest import build_model, spawn_qpos, verdict

LEVERS = {
    "default (16 steps per graph, unused features off)": {},
    "2 solver + 2 line-search iterations": {"options": {"iterations": 2, "ls_iterations": 2}},
    "CG solver": {"options": {"solver": 1}},
    "96 steps per graph": {"graph_steps": 96},
    "480 steps per graph": {"graph_steps": 480},
    "no graph conditionals": {"options": {"graph_conditional": False}},
    "run_qacc_smooth off": {"options": {"run_qacc_smooth": False}},
    "480 steps per graph, run_qacc_smooth off": {"graph_steps": 480, "options": {"run_qacc_smooth": False}},
    "early exit (sleeping)": {"early_exit": True},
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=1024)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=os.cpu_count())
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    config = DropTestConfig()
    chosen, bodies = bodies_for(args.count, 0)
    models = [build_model(b, 1, config) for b in bodies]
    qpos0 = np.stack([spawn_qpos(b) for b in bodies])
    c_row, ref = bench_c(bodies, config)
    rollout_row, _ = bench_rollout(bodies, config, args.threads)
    pb, status = pybullet_available()
    pb_row = bench_pybullet(pb, bodies, config)[0] if pb is not None else None
    rows, profile, first = [], None, None
    for name, lever in LEVERS.items():
        try:
            t0 = time.perf_counter()
            batch = warp_batch.prepare(models, qpos0, config, **lever)
            if profile is None:
                profile = kernel_profile(batch)
            setup = time.perf_counter() - t0
            out = batch.simulate()
            times = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                out = batch.simulate()
                times.append(time.perf_counter() - t0)
        except Exception as err:  # noqa: BLE001 — a lever that fails is recorded
            rows.append({"lever": name, "error": f"{type(err).__name__}: {err}"})
            continue
        run = statistics.median(times)
        res = [verdict(m, q, s, f, config, "warp") for m, q, s, f in zip(models, qpos0, out.settled, out.final)]
        first = out.final if first is None else first
        rows.append({"lever": name, "setup_s": setup, "run_s": run, "free_steps_run": out.free_steps_run,
                     "final_qpos_max_diff_vs_default": float(np.abs(out.final - first).max()),
                     "pybullet_over_warp": None if pb_row is None else pb_row["run_s"] / run,
                     "rollout_over_warp": rollout_row["run_s"] / run,
                     "vs_mujoco_c": agreement(chosen, ref, res)})
        print(rows[-1]["lever"], round(run, 4), flush=True)
    emit({"candidates": args.count, "mujoco_c_s": c_row["run_s"], "rollout": rollout_row,
          "pybullet": pb_row or status, "kernel_profile": profile, "levers": rows}, args.out)


def kernel_profile(batch, steps: int = 16, top: int = 15) -> dict:
    """The free phase's step launched kernel by kernel (no graph) under Warp's CUDA activity
    timing: kernels per step, their summed GPU time per step and the costliest ones."""
    import warp as wp

    if not batch.device.startswith("cuda"):
        return {"device": batch.device, "note": "kernel timing needs a CUDA device"}
    step = batch._steps()[1]
    with wp.ScopedDevice(batch.device):
        batch._reset()
        batch._phase(True)
        step()
        wp.synchronize()
        wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
        t0 = time.perf_counter()
        for _ in range(steps):
            step()
        wp.synchronize()
        eager = time.perf_counter() - t0
        results = wp.timing_end()
    by_name: dict[str, list[float]] = {}
    for r in results:
        by_name.setdefault(r.name, []).append(r.elapsed)
    rows = sorted(by_name.items(), key=lambda kv: -sum(kv[1]))
    return {"steps": steps, "kernels_per_step": len(results) / steps,
            "gpu_ms_per_step": sum(r.elapsed for r in results) / steps,
            "eager_wall_ms_per_step": 1e3 * eager / steps,
            "costliest": [{"kernel": k, "launches_per_step": len(v) / steps, "ms_per_step": sum(v) / steps}
                          for k, v in rows[:top]]}


if __name__ == "__main__":
    main()
