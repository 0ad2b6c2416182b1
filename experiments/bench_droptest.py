"""Benchmark of drop tests (the paper's protocol, 960 steps at 240 Hz); prints one JSON object.

Needs only jax, mujoco, mujoco-mjx, numpy and scipy; PyBullet and MuJoCo Warp are optional
(without them their rows are absent and ``pybullet`` / ``warp`` say why). The candidates are the procedural agreement cases
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
- ``rollout``: the honest CPU anchor, multi-threaded MuJoCo C (``mujoco.rollout``, ``--threads``,
  default every core of the host) on the same models;
- ``warp`` / ``warp_early_exit``: MuJoCo Warp, a world per candidate (``construct.physics.warp_batch``;
  host preparation + kernel load + CUDA-graph capture, first run, median run), without and with the
  early exit through MuJoCo's sleeping (its verdict changes are in ``agreement``);
- ``ratios``: MJX and Warp against the loops (C, rollout, PyBullet), run time alone and setup + run;
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

TARGET_GPU_RATIO = 50.0      # on a GPU: ≥ 50× the sequential PyBullet loop at 1024 candidates
TARGET_ROLLOUT_RATIO = 5.0   # ... and ≥ 5× multi-threaded MuJoCo C (mujoco.rollout, all host cores)


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


def _size_key(model: mujoco.MjModel) -> tuple:
    """Every size of the model (``n*``): an MjData serves only models of its own sizes, and the size
    signature leaves some out (mesh storage, the mass matrix's sparsity of a "simple" body)."""
    return tuple((name, getattr(model, name)) for name in sorted(dir(model))
                 if name.startswith("n") and isinstance(getattr(model, name), int))


def bench_rollout(bodies: list[DropBody], config: DropTestConfig, threads: int) -> tuple[dict, list]:
    """Multi-threaded MuJoCo C (``mujoco.rollout``, one thread per core): the same compiled models.
    An MjData serves only models of its own mesh sizes, so the candidates run in groups of equal
    sizes, each group's candidates in one call. Settling zeroes velocities after every step: one
    call per step there (the state goes back with qvel = 0; the solver's warm start restarts each
    call), then the free phase in one call per group."""
    from mujoco import rollout

    models = [build_model(b, 1, config) for b in bodies]
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    nq, nv = models[0].nq, models[0].nv
    qpos, qvel = slice(1, 1 + nq), slice(1 + nq, 1 + nq + nv)   # FULLPHYSICS: time, qpos, qvel, act, ...
    groups: dict[tuple, list[int]] = {}
    for k, m in enumerate(models):
        groups.setdefault(_size_key(m), []).append(k)
    runs = []
    for members in groups.values():
        ms = [models[k] for k in members]
        state = np.zeros((len(ms), mujoco.mj_stateSize(ms[0], spec)))
        for row, (m, k) in enumerate(zip(ms, members)):
            d = mujoco.MjData(m)
            d.qpos[:] = spawn_qpos(bodies[k])
            mujoco.mj_getState(m, d, state[row], spec)
        runs.append((members, ms, [mujoco.MjData(ms[0]) for _ in range(threads)], state,
                     np.empty((len(ms), 1, state.shape[1])), np.empty((len(ms), config.free_steps, state.shape[1])),
                     np.empty((len(ms), config.free_steps, 0))))
    settled, final = np.zeros((len(models), nq)), np.zeros((len(models), nq))
    t0 = time.perf_counter()
    with rollout.Rollout(nthread=threads) as pool:
        for members, ms, datas, state, one, out, sensors in runs:
            pool.rollout(ms, datas, state, nstep=1, state=one, sensordata=sensors[:, :1])   # checked once
        for step in range(config.settle_steps):
            for members, ms, datas, state, one, out, sensors in runs:
                if step:
                    pool.rollout(ms, datas, state, None, nstep=1, state=one, sensordata=sensors[:, :1],
                                 skip_checks=True)
                state[:] = one[:, 0]
                state[:, qvel] = 0.0
        for members, ms, datas, state, one, out, sensors in runs:
            settled[members] = state[:, qpos]
            pool.rollout(ms, datas, state, None, nstep=config.free_steps, state=out, sensordata=sensors,
                         skip_checks=True)
            final[members] = out[:, -1, qpos]
    run = time.perf_counter() - t0
    results = [verdict(m, spawn_qpos(b), s, f, config, "mujoco_rollout")
               for m, b, s, f in zip(models, bodies, settled, final)]
    steps = len(bodies) * (config.settle_steps + config.free_steps)
    return {"candidates": len(bodies), "threads": threads, "size_groups": len(runs), "run_s": run,
            "steps_per_s": steps / run}, results


def bench_warp(bodies: list[DropBody], config: DropTestConfig, repeats: int, early_exit: bool = False
               ) -> tuple[dict, list]:
    """MuJoCo Warp (``warp_batch``): host preparation, capture (kernel build/load + CUDA graphs),
    first run, then the median of ``repeats`` runs."""
    from phirie_jax.construct.physics import warp_batch

    models = [build_model(b, 1, config) for b in bodies]
    qpos0 = np.stack([spawn_qpos(b) for b in bodies])
    t0 = time.perf_counter()
    batch = warp_batch.prepare(models, qpos0, config, early_exit)
    prep_and_capture = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = batch.simulate()
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = batch.simulate()
        times.append(time.perf_counter() - t0)
    run = statistics.median(times) if times else first
    results = [verdict(m, q, s, f, config, "warp") for m, q, s, f in zip(models, qpos0, out.settled, out.final)]
    steps = len(bodies) * (config.settle_steps + config.free_steps)
    return {"candidates": len(bodies), "early_exit": early_exit, "device": out.device,
            "prep_and_capture_s": prep_and_capture, "first_run_s": first, "run_s": run,
            "free_steps_run": out.free_steps_run, "steps_per_s": steps / run}, results


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


def warp_available() -> tuple[bool, str]:
    from phirie_jax.construct.physics import warp_batch

    ok, why = warp_batch.available()
    return ok, f"available (warp {why})" if ok else why


def _ratios(count: int, runs: dict[str, dict]) -> dict:
    """Run-time ratios of the CPU loops (C, rollout, PyBullet) over each batched backend (MJX, Warp)."""
    ratio: dict = {"candidates": count}
    for fast in ("mjx", "warp", "warp_early_exit"):
        if fast not in runs:
            continue
        row = runs[fast]
        ratio[f"{fast}_run_s"] = row["run_s"]
        setup = row.get("compile_s", row.get("prep_and_capture_s", 0.0))
        ratio[f"{fast}_setup_plus_run_s"] = setup + row["run_s"]
        for slow, key in (("c", "c"), ("rollout", "rollout"), ("pybullet", "pybullet")):
            if slow in runs:
                ratio[f"{key}_over_{fast}_run"] = runs[slow]["run_s"] / row["run_s"]
        if "pybullet" in runs:
            ratio[f"pybullet_over_{fast}_setup_plus_run"] = runs["pybullet"]["run_s"] / ratio[f"{fast}_setup_plus_run_s"]
    return ratio


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
    parser.add_argument("--skip", nargs="*", default=(), choices=("c", "pybullet", "solver", "mjx", "warp", "rollout"))
    parser.add_argument("--threads", type=int, default=os.cpu_count(), help="mujoco.rollout threads (all cores)")
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
    warp_ok, warp_status = warp_available()
    result["warp"] = warp_status
    result.update(rollout_rows=[], warp_rows=[], warp_early_exit_rows=[])
    for count in sorted(args.counts):
        chosen, bodies = bodies_for(count, args.seed)
        runs: dict[str, dict] = {}
        if "mjx" not in args.skip:
            for bucket in args.buckets:
                bucket_config = dataclasses.replace(config, part_buckets=(bucket,))
                row, res = bench_mjx(bodies, bucket, bucket_config, args.repeats)
                row["traces_so_far"] = mjx_batch.TRACES["count"]
                result["mjx"].append(row)
                print(json.dumps({"mjx": row}), file=sys.stderr)
                if bucket == args.buckets[0]:
                    verdicts.setdefault(count, {})["mjx"] = res
                    runs["mjx"] = row
                elif count == largest:
                    result.setdefault("ghost_bucket_agreement", {})[str(bucket)] = agreement(
                        chosen, verdicts[count]["mjx"], res)
        timed = [("c", "mujoco_c", lambda: bench_c(bodies, config)),
                 ("rollout", "rollout_rows", lambda: bench_rollout(bodies, config, args.threads))]
        if warp_ok:
            timed += [("warp", "warp_rows", lambda: bench_warp(bodies, config, args.repeats)),
                      ("warp_early_exit", "warp_early_exit_rows",
                       lambda: bench_warp(bodies, config, args.repeats, early_exit=True))]
        if pb is not None and (args.pybullet_max is None or count <= args.pybullet_max):
            timed.append(("pybullet", "pybullet_rows", lambda: bench_pybullet(pb, bodies, config)))
        for name, key, bench in timed:
            if name.split("_")[0] in args.skip or name in result.get("errors", {}):
                continue
            try:
                row, res = bench()
            except Exception as err:  # noqa: BLE001 — one backend's failure is recorded, the others go on
                result.setdefault("errors", {})[name] = f"{type(err).__name__}: {err}"
                print(json.dumps({name: result["errors"][name]}), file=sys.stderr)
                continue
            verdicts.setdefault(count, {})[name] = res
            result[key].append(row)
            runs[name] = row
            print(json.dumps({name: row}), file=sys.stderr)
        result["ratios"].append(_ratios(count, runs))
        _save(result, args.out)
    if args.compile_repeats:
        result["compile_vs_count"] = compile_vs_count(sorted(args.counts), config, args.compile_repeats, args.seed)
        _save(result, args.out)
    chosen, bodies = bodies_for(largest, args.seed)
    v = verdicts[largest]
    result["agreement"] = {}
    if "c" in v:
        for name in ("mjx", "rollout", "warp", "warp_early_exit", "pybullet"):
            if name in v:
                result["agreement"][f"{name}_vs_mujoco_c"] = agreement(chosen, v["c"], v[name])
        result["agreement"]["mujoco_c_vs_statics"] = expected_accuracy(chosen, v["c"])
    for name in ("mjx", "warp", "pybullet"):
        if name in v:
            result["agreement"][f"{name}_vs_statics"] = expected_accuracy(chosen, v[name])
    if args.hard:
        hard = cases.hard_set(args.hard, args.seed + 1)
        hard_bodies = [body_from_parts((hull_part(c.vertices),), c.pose) for c in hard]
        _, ref = bench_c(hard_bodies, config)
        block = {"mujoco_c_stable_by_kind": {k: f"{sum(r.stable for c, r in zip(hard, ref) if c.kind == k)}/"
                                                f"{sum(c.kind == k for c in hard)} stable" for k in cases.KINDS_HARD}}
        others = {}
        if "mjx" not in args.skip:
            others["mjx"] = lambda: bench_mjx(hard_bodies, args.buckets[0], config, 0)
        if warp_ok and "warp" not in args.skip:
            others["warp"] = lambda: bench_warp(hard_bodies, config, 0)
            others["warp_early_exit"] = lambda: bench_warp(hard_bodies, config, 0, early_exit=True)
        if "rollout" not in args.skip:
            others["rollout"] = lambda: bench_rollout(hard_bodies, config, args.threads)
        if pb is not None and "pybullet" not in args.skip:
            others["pybullet"] = lambda: bench_pybullet(pb, hard_bodies, config)
        for name, bench in others.items():
            if name in result.get("errors", {}):
                continue
            try:
                _, res = bench()
            except Exception as err:  # noqa: BLE001
                result.setdefault("errors", {})[name] = f"{type(err).__name__}: {err}"
                continue
            block[f"{name}_vs_mujoco_c"] = agreement(hard, ref, res)
        result["agreement_hard"] = block
        _save(result, args.out)
    if "solver" not in args.skip:
        result["solver"] = solver_check(bodies, chosen, config)
    at_1024 = next((r for r in result["ratios"] if r["candidates"] == 1024), None) or {}
    fastest = min((k for k in ("mjx", "warp") if f"{k}_run_s" in at_1024), key=lambda k: at_1024[f"{k}_run_s"],
                  default=None)
    gpu = device.platform != "cpu"
    result["target"] = {
        "what": f"on a GPU, 1024 candidates ≥ {TARGET_GPU_RATIO:g}× sequential PyBullet and ≥ "
                f"{TARGET_ROLLOUT_RATIO:g}× mujoco.rollout on all host cores",
        "fastest": fastest,
        "pybullet_over_fastest": at_1024.get(f"pybullet_over_{fastest}_run") if fastest else None,
        "rollout_over_fastest": at_1024.get(f"rollout_over_{fastest}_run") if fastest else None,
        "met": (None if not gpu or fastest is None or f"pybullet_over_{fastest}_run" not in at_1024
                or f"rollout_over_{fastest}_run" not in at_1024
                else at_1024[f"pybullet_over_{fastest}_run"] >= TARGET_GPU_RATIO
                and at_1024[f"rollout_over_{fastest}_run"] >= TARGET_ROLLOUT_RATIO),
        "note": "" if gpu else "measured on a CPU: the target is for a GPU"}
    result["load_average_at_end"] = os.getloadavg()
    print(json.dumps(result, indent=2))
    _save(result, args.out)


if __name__ == "__main__":
    main()
