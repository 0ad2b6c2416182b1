"""Benchmark of drop tests (the paper's protocol, 960 steps at 240 Hz); prints one JSON object.

Needs only jax, mujoco, mujoco-mjx, numpy and scipy; PyBullet is optional (without it the
PyBullet rows say "unavailable" and why). The candidates are the procedural agreement cases
(``tests.fixtures.droptest_cases``: half stable, half unstable — cones on their tips, boxes
balanced on an edge, thin plates on their edge, tipped tall cylinders), one convex hull each,
the stand-in used while ranking candidates.

For each candidate count (default 1, 64, 256, 1024):

- ``mjx``: every candidate in one vmapped, jitted program (``interact.mjx_batch``): host
  preparation (compiling the C models, stacking), compilation (``.lower().compile()``, a
  fresh compile for every count, so compile time vs count is measured), run time (median of
  ``--repeats`` after a warm-up call, ``block_until_ready``), simulated steps per second
  (candidates × 960 / run time);
- ``mujoco_c``: the same compiled models stepped one after another by the C library (the
  reference; the settling phase is a Python loop since velocities are zeroed every step);
- ``pybullet``: what the paper used, one after another: reset, plane + convex-hull body
  with the same mass, centre of mass, friction and restitution 0, the same protocol;
- ``ratios``: MJX against both loops, run time alone and compile + run;
- ``compile_vs_count``: the batch program compiled ``--compile-repeats`` more times per count,
  interleaved across counts (a busy shared host slows some compiles: min and median);
- ``agreement``: verdicts of MJX and PyBullet against MuJoCo C on the largest set, per kind;
- ``agreement_hard``: the same on ``--hard`` cases near the protocol's edges (a box or cone
  0.3–1.5° past balance; small boxes toppling off an edge, drifting around the 3 cm threshold);
- ``solver``: our solver settings (``DropTestConfig``: 4 iterations, 4 line-search, tol 1e-6) against MuJoCo's
  defaults (100, 50, 1e-8): C on the largest set, MJX on 64 of its cases (verdicts, drift, time).

    python -m experiments.bench_droptest --out experiments/results/bench_droptest_cpu.json
    python -m experiments.bench_droptest --counts 1 64 256 1024 4096 --buckets 1 4 16   # a GPU
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import jax
import mujoco
import numpy as np

from phirie_jax.construct.physics import mjx_batch  # noqa: E402
from phirie_jax.construct.physics.collision import hull_part  # noqa: E402
from phirie_jax.construct.physics.config import DropTestConfig  # noqa: E402
from phirie_jax.construct.physics.droptest import (
    DropBody,
    body_from_parts,
    bucket_template,
    build_model,
    run_reference,
    spawn_qpos,
    verdict,
)
from tests.fixtures import droptest_cases as cases  # noqa: E402

TARGET_GPU_RATIO = 50.0   # issue 6: MJX on a GPU ≥ 50× the sequential PyBullet loop at 1024 candidates


def bodies_for(count: int, seed: int) -> tuple[list[cases.Case], list[DropBody]]:
    chosen = cases.case_set(count, seed)
    return chosen, [body_from_parts((hull_part(c.vertices),), c.pose) for c in chosen]


def bench_mjx(bodies: list[DropBody], bucket: int, config: DropTestConfig, repeats: int) -> tuple[dict, list]:
    t0 = time.perf_counter()
    template_model, template = bucket_template(bucket, config)
    models = [build_model(b, bucket, config) for b in bodies]
    qpos0 = np.stack([spawn_qpos(b) for b in bodies])
    params = mjx_batch.stack_params(template_model, models, config.vertex_budget)
    batch = mjx_batch.padded_count(len(bodies), config)
    idx = np.where(np.arange(batch) < len(bodies), np.arange(batch), 0)
    params = {k: v[idx] for k, v in params.items()}
    args = mjx_batch.device_args(template, params, qpos0[idx])
    prep = time.perf_counter() - t0
    t0 = time.perf_counter()
    compiled = mjx_batch.lower(template, params, qpos0[idx], config).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.block_until_ready(compiled(*args))
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - t0)
    run = statistics.median(times) if times else first
    settled, final = (np.asarray(o, np.float64)[: len(bodies)] for o in out)
    results = [verdict(m, q, s, f, config, "mjx") for m, q, s, f in zip(models, qpos0, settled, final)]
    steps = len(bodies) * (config.settle_steps + config.free_steps)
    return {"candidates": len(bodies), "batch": batch, "parts_bucket": bucket, "prep_s": prep,
            "compile_s": compile_s, "first_run_s": first, "run_s": run, "steps_per_s": steps / run,
            "candidates_per_s": len(bodies) / run}, results


def bench_c(bodies: list[DropBody], config: DropTestConfig) -> tuple[dict, list]:
    models = [build_model(b, 1, config) for b in bodies]
    qpos0 = [spawn_qpos(b) for b in bodies]
    t0 = time.perf_counter()
    runs = [run_reference(m, q, config) for m, q in zip(models, qpos0)]
    run = time.perf_counter() - t0
    results = [verdict(m, q, s, f, config, "mujoco") for m, q, (s, f) in zip(models, qpos0, runs)]
    steps = len(bodies) * (config.settle_steps + config.free_steps)
    return {"candidates": len(bodies), "run_s": run, "steps_per_s": steps / run}, results


def pybullet_available() -> tuple[object | None, str]:
    try:
        import pybullet
    except ImportError as err:
        return None, f"unavailable: {err} (pip install pybullet)"
    return pybullet, "available"


def bench_pybullet(pb, bodies: list[DropBody], config: DropTestConfig) -> tuple[dict, list]:
    """The paper's loop: one PyBullet world per candidate, the same protocol, read the base (COM)."""
    client = pb.connect(pb.DIRECT)
    results, build_s, step_s = [], 0.0, 0.0
    try:
        for body in bodies:
            t0 = time.perf_counter()
            pb.resetSimulation(physicsClientId=client)
            pb.setGravity(0, 0, -9.81, physicsClientId=client)
            pb.setTimeStep(config.timestep, physicsClientId=client)
            plane = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=client)
            ground = pb.createMultiBody(0, plane, physicsClientId=client)
            com = body.mass.com
            shape = pb.createCollisionShape(pb.GEOM_MESH, vertices=(body.parts[0].vertices - com).tolist(),
                                            physicsClientId=client)
            q = spawn_qpos(body)
            rot = body.rotation
            start = q[:3] + rot @ com
            quat_wxyz = q[3:]
            orn = [quat_wxyz[1], quat_wxyz[2], quat_wxyz[3], quat_wxyz[0]]
            uid = pb.createMultiBody(body.priors.mass, shape, basePosition=start.tolist(), baseOrientation=orn,
                                     physicsClientId=client)
            for u in (ground, uid):
                pb.changeDynamics(u, -1, lateralFriction=body.priors.friction, restitution=0.0,
                                  physicsClientId=client)
            t1 = time.perf_counter()
            for _ in range(config.settle_steps):
                pb.stepSimulation(physicsClientId=client)
                pb.resetBaseVelocity(uid, [0, 0, 0], [0, 0, 0], physicsClientId=client)
            settled = np.asarray(pb.getBasePositionAndOrientation(uid, physicsClientId=client)[0])
            for _ in range(config.free_steps):
                pb.stepSimulation(physicsClientId=client)
            final = np.asarray(pb.getBasePositionAndOrientation(uid, physicsClientId=client)[0])
            t2 = time.perf_counter()
            build_s, step_s = build_s + t1 - t0, step_s + t2 - t1
            drift = float(np.linalg.norm(final - start))
            stable = drift < config.max_drift and final[2] >= config.min_final_height
            results.append({"stable": bool(stable), "drift_m": drift, "settle_drift_m": float(np.linalg.norm(settled - start))})
    finally:
        pb.disconnect(client)
    steps = len(bodies) * (config.settle_steps + config.free_steps)
    total = build_s + step_s
    return {"candidates": len(bodies), "run_s": total, "build_s": build_s, "step_s": step_s,
            "steps_per_s": steps / total}, results


def agreement(chosen: list[cases.Case], ref: list, other: list) -> dict:
    same = [r.stable == (o["stable"] if isinstance(o, dict) else o.stable) for r, o in zip(ref, other)]
    per_kind: dict[str, list[int]] = {}
    for c, s in zip(chosen, same):
        per_kind.setdefault(c.kind, [0, 0])
        per_kind[c.kind][0] += int(s)
        per_kind[c.kind][1] += 1
    return {"cases": len(same), "agree": int(sum(same)), "fraction": float(np.mean(same)),
            "per_kind": {k: f"{a}/{n}" for k, (a, n) in sorted(per_kind.items())},
            "disagreements": [c.name for c, s in zip(chosen, same) if not s]}


def expected_accuracy(chosen: list[cases.Case], results: list) -> dict:
    ok = [c.expected_stable == (r["stable"] if isinstance(r, dict) else r.stable) for c, r in zip(chosen, results)]
    return {"fraction": float(np.mean(ok)), "wrong": [c.name for c, o in zip(chosen, ok) if not o]}


def solver_check(bodies: list[DropBody], chosen: list[cases.Case], config: DropTestConfig) -> dict:
    defaults = dataclasses.replace(config, solver_iterations=100, line_search_iterations=50, tolerance=1e-8)
    ours, _ = bench_c(bodies, config)
    ref_row, ref = bench_c(bodies, defaults)
    _, fast = bench_c(bodies, config)
    drift = [abs(a.drift_m - b.drift_m) for a, b in zip(ref, fast)]
    stable_drift = [d for d, c in zip(drift, chosen) if c.expected_stable]
    mjx_rows = {}
    sub = bodies[:64]
    for name, cfg in (("ours", config), ("mujoco_defaults", defaults)):
        row, res = bench_mjx(sub, 1, cfg, 1)
        mjx_rows[name] = (row, res)
    mjx = {"candidates": len(sub), "ours_run_s": mjx_rows["ours"][0]["run_s"],
           "defaults_run_s": mjx_rows["mujoco_defaults"][0]["run_s"],
           "same_verdicts": [r.stable for r in mjx_rows["ours"][1]] == [r.stable for r in mjx_rows["mujoco_defaults"][1]],
           "max_abs_drift_difference_m": max(abs(a.drift_m - b.drift_m) for a, b in
                                             zip(mjx_rows["ours"][1], mjx_rows["mujoco_defaults"][1]))}
    return {"mjx": mjx, "ours": {"iterations": config.solver_iterations, "ls_iterations": config.line_search_iterations,
                     "tolerance": config.tolerance, "steps_per_s": ours["steps_per_s"]},
            "mujoco_defaults": {"iterations": 100, "ls_iterations": 50, "tolerance": 1e-8,
                                "steps_per_s": ref_row["steps_per_s"]},
            "verdict_agreement": agreement(chosen, ref, fast),
            "max_abs_drift_difference_stable_m": max(stable_drift) if stable_drift else None,
            "median_abs_drift_difference_m": float(np.median(drift))}


def compile_vs_count(counts: list[int], config: DropTestConfig, repeats: int, seed: int) -> dict:
    """Fresh compiles of the bucket-1 program for each count, interleaved: {count: seconds}."""
    template_model, template = bucket_template(1, config)
    inputs = {}
    for count in counts:
        _, bodies = bodies_for(count, seed)
        models = [build_model(b, 1, config) for b in bodies]
        qpos0 = np.stack([spawn_qpos(b) for b in bodies])
        params = mjx_batch.stack_params(template_model, models, config.vertex_budget)
        batch = mjx_batch.padded_count(count, config)
        idx = np.where(np.arange(batch) < count, np.arange(batch), 0)
        inputs[count] = ({k: v[idx] for k, v in params.items()}, qpos0[idx])
    times: dict[int, list[float]] = {c: [] for c in counts}
    for _ in range(repeats):
        for count in counts:
            jax.clear_caches()          # else the in-memory executable cache answers in a millisecond
            lowered = mjx_batch.lower(template, *inputs[count], config)   # a Lowered keeps its executable
            t0 = time.perf_counter()
            lowered.compile()
            times[count].append(time.perf_counter() - t0)
    return {str(c): {"batch": mjx_batch.padded_count(c, config), "compile_s": t, "min_s": min(t),
                     "median_s": statistics.median(t)} for c, t in times.items()}


def _save(result: dict, out: Path | None) -> None:
    if out:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=2) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[1, 64, 256, 1024])
    parser.add_argument("--buckets", type=int, nargs="+", default=[1],
                        help="part buckets timed for MJX (ghost-padded single hulls: the cost of P parts)")
    parser.add_argument("--repeats", type=int, default=1, help="timed MJX runs after the warm-up call")
    parser.add_argument("--pybullet-max", type=int, default=None, help="cap PyBullet at this many candidates")
    parser.add_argument("--skip", nargs="*", default=(), choices=("c", "pybullet", "solver"))
    parser.add_argument("--compile-repeats", type=int, default=2, help="extra interleaved compiles per count")
    parser.add_argument("--hard", type=int, default=256, help="cases of the hard agreement set (0: none)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()

    config = DropTestConfig()
    device = jax.devices()[0]
    pb, pb_status = pybullet_available()
    from mujoco import mjx

    result: dict = {
        "device": str(device), "device_kind": getattr(device, "device_kind", device.platform),
        "platform": device.platform, "host": platform.processor() or platform.machine(),
        "jax": jax.__version__, "mujoco": mujoco.__version__, "mujoco_mjx": getattr(mjx, "__version__", None),
        "pybullet": pb_status if pb is None else f"{pb_status} (API {pb.getAPIVersion()})",
        "pybullet_module": None if pb is None else pb.__file__,
        "protocol": {"timestep_s": config.timestep, "settle_steps": config.settle_steps,
                     "free_steps": config.free_steps, "vertex_budget": config.vertex_budget,
                     "solver_iterations": config.solver_iterations,
                     "line_search_iterations": config.line_search_iterations, "tolerance": config.tolerance},
        "load_average_at_start": os.getloadavg(),
        "mjx": [], "mujoco_c": [], "pybullet_rows": [], "ratios": []}
    largest = max(args.counts)
    verdicts: dict = {}
    for count in sorted(args.counts):
        chosen, bodies = bodies_for(count, args.seed)
        for bucket in args.buckets:
            bucket_config = dataclasses.replace(config, part_buckets=(bucket,))
            row, res = bench_mjx(bodies, bucket, bucket_config, args.repeats)
            row["traces_so_far"] = mjx_batch.TRACES["count"]
            result["mjx"].append(row)
            print(json.dumps({"mjx": row}), file=sys.stderr)
            if bucket == args.buckets[0]:
                verdicts.setdefault(count, {})["mjx"] = res
            elif count == largest:
                result.setdefault("ghost_bucket_agreement", {})[str(bucket)] = agreement(
                    chosen, verdicts[count]["mjx"], res)
        c_row = None
        if "c" not in args.skip:
            c_row, res = bench_c(bodies, config)
            verdicts[count]["c"] = res
            result["mujoco_c"].append(c_row)
            print(json.dumps({"mujoco_c": c_row}), file=sys.stderr)
        pb_row = None
        if pb is not None and "pybullet" not in args.skip and (args.pybullet_max is None or count <= args.pybullet_max):
            pb_row, res = bench_pybullet(pb, bodies, config)
            verdicts[count]["pybullet"] = res
            result["pybullet_rows"].append(pb_row)
            print(json.dumps({"pybullet": pb_row}), file=sys.stderr)
        m = result["mjx"][-len(args.buckets)]
        ratio = {"candidates": count, "mjx_run_s": m["run_s"], "mjx_compile_plus_run_s": m["compile_s"] + m["run_s"]}
        if c_row:
            ratio["c_over_mjx_run"] = c_row["run_s"] / m["run_s"]
        if pb_row:
            ratio["pybullet_over_mjx_run"] = pb_row["run_s"] / m["run_s"]
            ratio["pybullet_over_mjx_compile_plus_run"] = pb_row["run_s"] / (m["compile_s"] + m["run_s"])
        result["ratios"].append(ratio)
        _save(result, args.out)
    if args.compile_repeats:
        result["compile_vs_count"] = compile_vs_count(sorted(args.counts), config, args.compile_repeats, args.seed)
        _save(result, args.out)
    chosen, bodies = bodies_for(largest, args.seed)
    v = verdicts[largest]
    result["agreement"] = {}
    if "c" in v:
        result["agreement"]["mjx_vs_mujoco_c"] = agreement(chosen, v["c"], v["mjx"])
        result["agreement"]["mujoco_c_vs_statics"] = expected_accuracy(chosen, v["c"])
        if "pybullet" in v:
            result["agreement"]["pybullet_vs_mujoco_c"] = agreement(chosen, v["c"], v["pybullet"])
    result["agreement"]["mjx_vs_statics"] = expected_accuracy(chosen, v["mjx"])
    if "pybullet" in v:
        result["agreement"]["pybullet_vs_statics"] = expected_accuracy(chosen, v["pybullet"])
    if args.hard:
        hard = cases.hard_set(args.hard, args.seed + 1)
        hard_bodies = [body_from_parts((hull_part(c.vertices),), c.pose) for c in hard]
        _, fast = bench_mjx(hard_bodies, args.buckets[0], config, 0)
        _, ref = bench_c(hard_bodies, config)
        block = {"mjx_vs_mujoco_c": agreement(hard, ref, fast),
                 "mujoco_c_stable_by_kind": {k: f"{sum(r.stable for c, r in zip(hard, ref) if c.kind == k)}/"
                                                f"{sum(c.kind == k for c in hard)} stable" for k in cases.KINDS_HARD}}
        if pb is not None and "pybullet" not in args.skip:
            _, pbr = bench_pybullet(pb, hard_bodies, config)
            block["pybullet_vs_mujoco_c"] = agreement(hard, ref, pbr)
        result["agreement_hard"] = block
        _save(result, args.out)
    if "solver" not in args.skip:
        result["solver"] = solver_check(bodies, chosen, config)
    at_1024 = next((r for r in result["ratios"] if r["candidates"] == 1024), None)
    result["target"] = {
        "what": f"on a GPU, MJX drop-tests 1024 candidates ≥ {TARGET_GPU_RATIO:g}× faster than sequential PyBullet",
        "pybullet_over_mjx_run_at_1024": None if not at_1024 else at_1024.get("pybullet_over_mjx_run"),
        "met": (None if device.platform == "cpu" or not at_1024 or "pybullet_over_mjx_run" not in at_1024
                else at_1024["pybullet_over_mjx_run"] >= TARGET_GPU_RATIO),
        "note": "measured on a CPU: the target is for a GPU" if device.platform == "cpu" else ""}
    result["load_average_at_end"] = os.getloadavg()
    print(json.dumps(result, indent=2))
    _save(result, args.out)


if __name__ == "__main__":
    main()
