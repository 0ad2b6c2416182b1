"""Tuning the MJX drop test: solver iterations, loop unrolling and XLA flags; prints one JSON object.

The drop test's MJX program is latency-bound on a GPU (a step is a chain of small kernels and
of solver loops), so its run time depends on how many sequential iterations a step takes and
on how XLA launches them, far more than on the candidate count. For each setting this measures
the MJX run time at 1 and at ``--count`` candidates, and what the setting costs in fidelity:

- ``solver``: Newton or CG, its iterations and line-search iterations, and a dense or sparse
  mass matrix (MJX's dense path factors with cuSOLVER calls, its sparse path does not), the
  same for MJX and MuJoCo C;
- ``unroll``: steps per loop iteration of the protocol's scans;
- ``xla_flags``: each flag set runs in its own process (XLA reads its flags once).

Fidelity of a solver setting, on the benchmark's case set and on the hard set (cases near the
protocol's edges): verdicts of MuJoCo C with that setting against the statics' expectation and
against MuJoCo C with MuJoCo's default solver (100 iterations, 50 line-search, tol 1e-8), and
MJX against MuJoCo C with the same setting (the issue's ≥ 98 % agreement). MuJoCo C runs in a
process pool here (only its verdicts are used; ``bench_droptest.py`` times it).

    python -m experiments.droptest_tuning --solver newton:20,10 newton:4,4 cg:10,4:sparse --unroll 1 4 \\
        --xla-flags default "xla_gpu_enable_command_buffer=FUSION,CUBLAS,CUSTOM_CALL,WHILE,CONDITIONAL"
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from phirie_jax.construct.physics.collision import hull_part  # noqa: E402
from phirie_jax.construct.physics.config import DropTestConfig  # noqa: E402
from phirie_jax.construct.physics.droptest import body_from_parts, build_model, run_reference, spawn_qpos, verdict  # noqa: E402
from tests.fixtures import droptest_cases as cases  # noqa: E402

DEFAULT_SOLVER = "newton:100,50:dense:1e-8"   # MuJoCo's own solver settings


def solver_config(spec: str, unroll: int = 1) -> DropTestConfig:
    """``solver:iterations,ls_iterations[:jacobian[:tolerance]]``, e.g. "newton:4,4" or "cg:10,4:sparse"."""
    fields = spec.split(":")
    iterations, ls_iterations = (int(v) for v in fields[1].split(","))
    base = DropTestConfig()
    return dataclasses.replace(base, solver=fields[0], solver_iterations=iterations,
                               line_search_iterations=ls_iterations,
                               jacobian=fields[2] if len(fields) > 2 else base.jacobian,
                               tolerance=float(fields[3]) if len(fields) > 3 else base.tolerance, unroll=unroll)


def case_bodies(which: str, count: int, seed: int):
    chosen = cases.case_set(count, seed) if which == "main" else cases.hard_set(count, seed + 1)
    return chosen, [body_from_parts((hull_part(c.vertices),), c.pose) for c in chosen]


def _c_verdicts(job: tuple) -> list[tuple[bool, float]]:
    which, count, seed, solver, lo, hi = job
    config = solver_config(solver)
    _, bodies = case_bodies(which, count, seed)
    out = []
    for body in bodies[lo:hi]:
        model, q0 = build_model(body, 1, config), spawn_qpos(body)
        out.append(_verdict(verdict(model, q0, *run_reference(model, q0, config), config, "mujoco")))
    return out


def _verdict(result) -> tuple[bool, float]:
    """(stable, drift); a diverged simulation is unstable with a NaN drift."""
    return bool(result.stable), float("nan") if result.drift_m is None else float(result.drift_m)


def c_verdicts(which: str, count: int, seed: int, solver: str, pool: ProcessPoolExecutor) -> list:
    step = max(1, count // (4 * (os.cpu_count() or 1)))
    jobs = [(which, count, seed, solver, lo, min(count, lo + step)) for lo in range(0, count, step)]
    return [v for chunk in pool.map(_c_verdicts, jobs) for v in chunk]


def child(args) -> dict:
    """MJX timings and verdicts of every (solver, unroll) under this process's XLA flags."""
    import jax

    from experiments.bench_droptest import bench_mjx

    rows = []
    for solver in args.solver:
        for unroll in args.unroll:
            config = solver_config(solver, unroll=unroll)
            row = {"solver": solver, "unroll": unroll}
            for which, count in (("one", 1), ("main", args.count), ("hard", args.hard)):
                if not count or (which == "hard" and unroll != args.unroll[0]):
                    continue
                _, bodies = case_bodies("main" if which == "one" else which, count, args.seed)
                timing, res = bench_mjx(bodies, 1, config, args.repeats)
                row[which] = {k: timing[k] for k in ("batch", "compile_s", "run_s", "steps_per_s")}
                if which != "one":
                    row[which]["verdicts"] = [_verdict(r) for r in res]
                    row[which]["diverged"] = sum(r.error is not None for r in res)
                print(json.dumps({k: (v if k in ("solver", "unroll") else
                                      {a: b for a, b in v.items() if a != "verdicts"}) for k, v in row.items()}),
                      file=sys.stderr, flush=True)
            rows.append(row)
    return {"device": str(jax.devices()[0]), "rows": rows}


def agreement(a: list, b: list) -> dict:
    same = [x[0] == y[0] for x, y in zip(a, b)]
    drift = [abs(x[1] - y[1]) for x, y in zip(a, b)]
    return {"fraction": float(np.mean(same)), "disagree": int(len(same) - sum(same)),
            "diverged": int(sum(np.isnan(y[1]) for y in b)),
            "median_abs_drift_difference_m": float(np.nanmedian(drift))}


def statics(chosen: list, got: list) -> dict:
    decided = [(c.expected_stable, g[0]) for c, g in zip(chosen, got) if c.expected_stable is not None]
    return {"fraction": float(np.mean([e == g for e, g in decided])) if decided else None, "cases": len(decided)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--solver", nargs="+", default=["newton:20,10", "newton:4,4"],
                        help="solver:iterations,ls_iterations[:jacobian[:tolerance]] (e.g. cg:10,4:sparse)")
    parser.add_argument("--unroll", type=int, nargs="+", default=[1])
    parser.add_argument("--xla-flags", nargs="+", default=["default"],
                        help='flag sets, each "default" or XLA flags without their leading "--", separated by ";"')
    parser.add_argument("--count", type=int, default=1024)
    parser.add_argument("--hard", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--skip-c", action="store_true", help="timings only")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args)))
        return

    result: dict = {"count": args.count, "hard": args.hard, "settle_free_steps": [DropTestConfig().settle_steps,
                    DropTestConfig().free_steps], "runs": []}
    base = [sys.executable, __file__, "--child", "--count", str(args.count),
            "--repeats", str(args.repeats), "--seed", str(args.seed), "--unroll", *map(str, args.unroll),
            "--solver", *args.solver]
    for n, flags in enumerate(args.xla_flags):   # verdicts do not depend on the flags: the hard set once
        extra = "" if flags == "default" else " ".join("--" + f.strip() for f in flags.split(";"))
        env = dict(os.environ, XLA_FLAGS=" ".join(filter(None, (os.environ.get("XLA_FLAGS", ""), extra))),
                   PYTHONPATH=os.pathsep.join(filter(None, (str(Path(__file__).resolve().parents[1]),
                                                             os.environ.get("PYTHONPATH")))))
        t0 = time.perf_counter()
        proc = subprocess.run(base + ["--hard", str(args.hard if n == 0 else 0)], env=env, stdout=subprocess.PIPE, text=True)
        run = {"xla_flags": flags, "wall_s": time.perf_counter() - t0, "returncode": proc.returncode}
        if proc.returncode == 0:
            run.update(json.loads(proc.stdout.strip().splitlines()[-1]))
        result["runs"].append(run)
        _save(result, args.out)
    if not args.skip_c:
        with ProcessPoolExecutor() as pool:
            sets = {"main": (cases.case_set(args.count, args.seed), args.count),
                    "hard": (cases.hard_set(args.hard, args.seed + 1), args.hard)}
            reference = {w: c_verdicts(w, n, args.seed, DEFAULT_SOLVER, pool)
                         for w, (_, n) in sets.items() if n}
            fidelity = {}
            for solver in args.solver:
                entry = {}
                for which, (chosen, n) in sets.items():
                    if not n:
                        continue
                    c = c_verdicts(which, n, args.seed, solver, pool)
                    block = {"c_vs_statics": statics(chosen, c), "c_vs_c_default_solver": agreement(reference[which], c)}
                    for run in result["runs"]:
                        for row in run.get("rows", []):
                            if row["solver"] == solver and which in row:
                                block[f"mjx_vs_c[{run['xla_flags']}|unroll {row['unroll']}]"] = \
                                    agreement(c, row[which]["verdicts"])
                    entry[which] = block
                fidelity[solver] = entry
            result["fidelity"] = fidelity
            result["c_default_solver_vs_statics"] = {w: statics(sets[w][0], v) for w, v in reference.items()}
    for run in result["runs"]:
        for row in run.get("rows", []):
            for which in ("main", "hard"):
                row.get(which, {}).pop("verdicts", None)
    print(json.dumps(result, indent=2))
    _save(result, args.out)


def _save(result: dict, out: Path | None) -> None:
    if out:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
