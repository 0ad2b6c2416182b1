"""Benchmark of batched Sim(3) registration (``kernels.registration``); prints one JSON object.

Needs only jax, numpy and scipy (Open3D is optional: without it the Open3D baseline is
skipped and the JSON says so). The object is a procedural mug sampled with NumPy (20K
points, the paper's count) in a random canonical frame (random signed up axis, yaw,
unit-box scale); the observation Q is the part of it seen from three cameras on one
side (no bottom), as the observation stage would give.

Measured, each with compile time (``.lower().compile()``) apart from run time (median
of ``--repeats`` after a warm-up, ``block_until_ready``):

- ``search``: the whole registration program (sweep of 6 axes × 36 yaws × 3 scales, top-1
  per axis refined by 20 ICP + 10 scale iterations, rescored on the full sets) with all six
  axes in one call, with the candidate's own up (+z) only, and with the five others only:
  what the retry costs batched (all / own) and lazily ((own + others) / own). Hypotheses/s
  counts the sweep's hypotheses.
- ``sweep``: scoring alone, hypotheses/s, on the sweep subsets and on the full sets.
- ``nearest``: d_τ(SP, Q) on the full sets by chunked brute force and by the voxel-hash grid.
- ``icp``: the same work hypothesis by hypothesis — point-to-point ICP of the same
  initial hypotheses, same point counts, same max correspondence distance, 20 iterations:
  ours batched (vmap) vs the loop a user would write with Open3D
  (``registration_icp`` per hypothesis; it builds its KD-tree inside each call).

    python -m experiments.bench_register --out experiments/results/bench_register_cpu.json
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from experiments.report import emit
from kernels.chamfer import build_grid, nearest_grid, nearest_sq  # noqa: E402
from kernels.registration import UP_AXES, SearchSpec, axis_rotation, hypothesis_energy, icp, place, register, yaw_matrix  # noqa: E402

TAU = 0.03
MAX_CORR = 0.06


# --- a procedural object and its partial observation --------------------------------------


def mug(n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) points and normals on a mug (outer and inner wall, floor, rim, handle), z up, metres."""
    r, ri, h, floor = 0.04, 0.035, 0.1, 0.008
    parts = {  # name: area
        "outer": 2 * np.pi * r * h, "inner": 2 * np.pi * ri * (h - floor), "bottom": np.pi * r * r,
        "floor": np.pi * ri * ri, "rim": np.pi * (r * r - ri * ri), "handle": 2 * np.pi * 0.006 * np.pi * 0.028,
    }
    names = list(parts)
    counts = rng.multinomial(n, np.array([parts[k] for k in names]) / sum(parts.values()))
    pts, nrm = [], []
    for name, c in zip(names, counts):
        a = rng.uniform(0, 2 * np.pi, c)
        if name in ("outer", "inner"):
            rad = r if name == "outer" else ri
            z = rng.uniform(0 if name == "outer" else floor, h, c)
            p = np.stack([rad * np.cos(a), rad * np.sin(a), z], 1)
            nn = np.stack([np.cos(a), np.sin(a), np.zeros(c)], 1) * (1 if name == "outer" else -1)
        elif name in ("bottom", "floor", "rim"):
            lo, hi = (0, r) if name == "bottom" else (0, ri) if name == "floor" else (ri, r)
            rad = np.sqrt(rng.uniform(lo * lo, hi * hi, c))
            z = {"bottom": 0.0, "floor": floor, "rim": h}[name]
            p = np.stack([rad * np.cos(a), rad * np.sin(a), np.full(c, z)], 1)
            nn = np.tile([0, 0, -1.0 if name == "bottom" else 1.0], (c, 1))
        else:
            u = rng.uniform(-np.pi / 2, np.pi / 2, c)
            centre = np.stack([r - 0.004 + 0.028 * np.cos(u), np.zeros(c), 0.5 * h + 0.028 * np.sin(u)], 1)
            radial = np.stack([np.cos(u) * np.cos(a), np.sin(a), np.sin(u) * np.cos(a)], 1)
            p, nn = centre + 0.006 * radial, radial
        pts.append(p)
        nrm.append(nn)
    return np.concatenate(pts), np.concatenate(nrm)


def observe(points: np.ndarray, normals: np.ndarray, count: int, rng) -> np.ndarray:
    """Points facing one of three cameras on one side (elevation 35°), above the table."""
    az = np.radians([-40.0, 0.0, 40.0])
    cams = 0.6 * np.stack([np.cos(az) * np.cos(0.6), np.sin(az) * np.cos(0.6), np.full(3, np.sin(0.6))], 1)
    facing = np.any(np.einsum("nd,cnd->cn", normals, cams[:, None, :] - points[None]) > 0, axis=0)
    seen = points[facing & (points[:, 2] > 0.003)]
    return seen[rng.choice(len(seen), size=min(count, len(seen)), replace=False)]


def candidate(points: np.ndarray, rng) -> tuple[np.ndarray, np.ndarray]:
    """The object in a random canonical frame: → (points, 4×4 truth canonical → world)."""
    axis = UP_AXES[rng.integers(6)]
    yaw = rng.uniform(0, 2 * np.pi)
    to_file = axis_rotation(axis).T @ np.asarray(yaw_matrix(jnp.float32(yaw)), np.float64)
    p = points @ to_file.T
    centre, size = p.mean(0), float(np.max(p.max(0) - p.min(0)))
    p = (p - centre) / size
    truth = np.eye(4)
    truth[:3, :3] = size * to_file.T
    truth[:3, 3] = to_file.T @ centre
    return p.astype(np.float32), truth


# --- timing helpers ---------------------------------------------------------------------


def timed_compile(jitted, *args):
    t = time.perf_counter()
    compiled = jitted.lower(*args).compile()
    return compiled, time.perf_counter() - t


def median_s(fn, repeats: int) -> float:
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def pad(q: np.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    n = max(256, 1 << (len(q) - 1).bit_length())
    out = np.zeros((n, 3), np.float32)
    out[: len(q)] = q
    mask = np.zeros(n, bool)
    mask[: len(q)] = True
    return jnp.asarray(out), jnp.asarray(mask)


# --- measurements -------------------------------------------------------------------------


def bench_search(model, obs, mask, truth, repeats, batch):
    args = (model, obs, mask, jnp.float32(0.0), jnp.bool_(True), jnp.float32(TAU), jnp.float32(MAX_CORR))
    out = {}
    for name, axes in (("all_axes", (0, 1, 2, 3, 4, 5)), ("own_axis", (0,)), ("other_axes", (1, 2, 3, 4, 5))):
        spec = SearchSpec(axes=axes, snap_to_support=True, hypothesis_batch=batch)
        fn = jax.jit(register, static_argnames=("spec",))
        compiled, compile_s = timed_compile(fn, *args, spec)
        run_s = median_s(lambda: compiled(*args), repeats)
        res = jax.device_get(compiled(*args))
        best = int(np.argmin(res.energy))
        placed = float(res.scale[best]) * np.asarray(res.rotation[best])
        out[name] = {"hypotheses": spec.num_hypotheses, "compile_s": round(compile_s, 3), "run_s": round(run_s, 4),
                     "hypotheses_per_s": round(spec.num_hypotheses / run_s, 1),
                     "best_energy_m": round(float(res.energy[best]), 5),
                     "rotation_scale_error": round(float(np.abs(placed - truth[:3, :3]).max() / np.cbrt(
                         abs(np.linalg.det(truth[:3, :3])))), 4)}
    own, other, both = (out[k]["run_s"] for k in ("own_axis", "other_axes", "all_axes"))
    out["retry_cost"] = {"batched_all_over_own": round(both / own, 3),
                         "lazy_own_plus_others_over_own": round((own + other) / own, 3),
                         "note": "batched: retry is a host-side choice after one call; lazy: a second call"}
    return out


def hypotheses(model, obs, mask, spec: SearchSpec):
    """The sweep's initial hypotheses (rotation, scale, translation), as ``register`` makes them."""
    from kernels.registration import robust_extents, scale_init

    q = jnp.where(mask[:, None], obs, jnp.nan)
    q_lo, q_hi = jnp.nanquantile(q, jnp.array([0.02, 0.98]), axis=0)
    axis_rots = jnp.asarray(np.stack([axis_rotation(UP_AXES[a]) for a in spec.axes]), jnp.float32)
    s0 = jax.vmap(lambda r: scale_init(model[:2048] @ r.T, robust_extents(obs, mask)))(axis_rots)
    yaws = jnp.arange(spec.num_yaws, dtype=jnp.float32) * (2 * np.pi / spec.num_yaws)
    a, y, m = (g.reshape(-1) for g in jnp.meshgrid(jnp.arange(len(spec.axes)), jnp.arange(spec.num_yaws),
                                                    jnp.arange(len(spec.scale_multipliers)), indexing="ij"))
    rots = yaw_matrix(yaws[y]) @ axis_rots[a]
    scales = s0[a] * jnp.asarray(spec.scale_multipliers, jnp.float32)[m]
    centre = 0.5 * (q_lo[:2] + q_hi[:2])
    trans = jax.vmap(lambda r, s: place(model[:2048], r, s, centre, jnp.float32(0.0)))(rots, scales)
    return rots, scales, trans


def bench_sweep(model, obs, mask, spec, repeats, full_count):
    rots, scales, trans = hypotheses(model, obs, mask, spec)
    out = {}
    for name, (p, q, m, count) in {
        "subsets": (model[: spec.sweep_model_points], obs[: spec.sweep_obs_points], mask[: spec.sweep_obs_points],
                    len(rots)),
        "full_sets": (model, obs, mask, full_count),
    }.items():
        def sweep(p, q, m, rots, scales, trans):
            f = lambda h: hypothesis_energy(p, q, m, h[0], h[1], h[2], TAU, spec.chunk)[0]  # noqa: E731
            return jax.lax.map(f, (rots, scales, trans), batch_size=spec.hypothesis_batch)

        args = (p, q, m, rots[:count], scales[:count], trans[:count])
        compiled, compile_s = timed_compile(jax.jit(sweep), *args)
        run_s = median_s(lambda: compiled(*args), repeats)
        out[name] = {"model_points": int(p.shape[0]), "obs_points": int(m.sum()), "obs_padded": int(q.shape[0]),
                     "hypotheses": int(count), "compile_s": round(compile_s, 3), "run_s": round(run_s, 4),
                     "hypotheses_per_s": round(count / run_s, 1),
                     "point_pairs_per_s": float(f"{2 * count * p.shape[0] * q.shape[0] / run_s:.3g}")}
    return out


def bench_nearest(model, obs, mask, repeats, batch=36):
    """d_τ(SP, Q) for ``batch`` placements of the full P: brute force vs the hash grid of Q."""
    rng = np.random.default_rng(1)
    shifts = jnp.asarray(rng.normal(0, 0.01, (batch, 3)), jnp.float32)
    placed = model * 0.1  # unit box → ~10 cm, like the object

    def brute(shifts):
        f = lambda s: jnp.mean(jnp.minimum(jnp.sqrt(nearest_sq(placed + s, obs, mask)), TAU))  # noqa: E731
        return jax.lax.map(f, shifts, batch_size=6)

    probe = build_grid(obs, mask, TAU, table_size=4096, capacity=1)
    capacity = 1 << int(np.asarray(probe.count).max() - 1).bit_length()  # no slot overflows: exact

    def grid(shifts):
        g = build_grid(obs, mask, TAU, table_size=4096, capacity=capacity)
        f = lambda s: jnp.mean(jnp.minimum(jnp.sqrt(nearest_grid(placed + s, g)), TAU))  # noqa: E731
        return jax.lax.map(f, shifts, batch_size=6), g.overflow

    out = {}
    for name, fn in (("brute_force", brute), ("hash_grid", grid)):
        print(f"nearest: {name}", file=sys.stderr, flush=True)
        compiled, compile_s = timed_compile(jax.jit(fn), shifts)
        run_s = median_s(lambda: compiled(shifts), repeats)
        out[name] = {"compile_s": round(compile_s, 3), "run_s": round(run_s, 4),
                     "placements_per_s": round(batch / run_s, 1)}
    b = np.asarray(jax.jit(brute)(shifts))
    g, overflow = jax.jit(grid)(shifts)
    out["max_abs_difference_m"] = float(np.abs(b - np.asarray(g)).max())
    out["grid_overflow"] = bool(overflow)
    out["grid_capacity"] = capacity
    out["speedup_grid_over_brute"] = round(out["brute_force"]["run_s"] / out["hash_grid"]["run_s"], 3)
    return out


def bench_icp(model, obs, mask, spec, repeats, o3d_count):
    rots, scales, trans = hypotheses(model, obs, mask, spec)
    p = model[: spec.icp_model_points]
    n_obs = min(spec.icp_obs_points, obs.shape[0])
    q, m = obs[:n_obs], mask[:n_obs]

    def ours(rots, scales, trans):
        f = lambda h: icp(p, q, m, h[0], h[1], h[2], jnp.float32(MAX_CORR), spec.icp_iterations,  # noqa: E731
                          False, spec.chunk)
        return jax.lax.map(f, (rots, scales, trans), batch_size=spec.hypothesis_batch)

    args = (rots, scales, trans)
    compiled, compile_s = timed_compile(jax.jit(ours), *args)
    run_s = median_s(lambda: compiled(*args), max(1, repeats // 2))
    out = {"hypotheses": int(len(rots)), "iterations": spec.icp_iterations, "model_points": int(p.shape[0]),
           "obs_points": int(np.asarray(m).sum()),
           "ours": {"compile_s": round(compile_s, 3), "run_s": round(run_s, 4),
                    "hypotheses_per_s": round(len(rots) / run_s, 1)}}
    try:
        import open3d as o3d
    except ImportError:
        out["open3d"] = {"skipped": "open3d is not installed"}
        return out
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(q)[np.asarray(m)].astype(np.float64)))
    criteria = o3d.pipelines.registration.ICPConvergenceCriteria(relative_fitness=0.0, relative_rmse=0.0,
                                                                 max_iteration=spec.icp_iterations)
    estimation = o3d.pipelines.registration.TransformationEstimationPointToPoint(with_scaling=False)
    rots_np, scales_np, trans_np = (np.asarray(x, np.float64) for x in (rots, scales, trans))
    count = min(o3d_count, len(rots_np))
    t = time.perf_counter()
    for i in range(count):
        # the user's loop: the candidate scaled by the hypothesis, Q registered onto it
        tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scales_np[i] * np.asarray(p, np.float64)))
        init = np.eye(4)
        init[:3, :3] = rots_np[i].T
        init[:3, 3] = -rots_np[i].T @ trans_np[i]
        o3d.pipelines.registration.registration_icp(src, tgt, MAX_CORR, init, estimation, criteria)
    o3d_s = time.perf_counter() - t
    per_s = count / o3d_s
    out["open3d"] = {"version": o3d.__version__, "hypotheses_timed": count, "run_s": round(o3d_s, 3),
                     "hypotheses_per_s": round(per_s, 1), "threads": "Open3D default"}
    out["speedup_ours_over_open3d"] = round(out["ours"]["hypotheses_per_s"] / per_s, 2)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--obs-points", type=int, default=2000, help="points in Q (observed)")
    parser.add_argument("--full-hypotheses", type=int, default=None,
                        help="hypotheses scored on the full sets (default: 36 on CPU, all on a GPU)")
    parser.add_argument("--open3d-hypotheses", type=int, default=72, help="hypotheses timed in the Open3D loop")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--hypothesis-batch", type=int, default=None,
                        help="hypotheses vmapped together (default: 36 on CPU, all 648 on a GPU)")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--skip", nargs="*", default=(), choices=("search", "sweep", "nearest", "icp"))
    args = parser.parse_args()

    rng = np.random.default_rng(args.seed)
    points, normals = mug(20_000, rng)
    q = observe(points, normals, args.obs_points, rng)
    model_np, truth = candidate(points, rng)
    model = jnp.asarray(model_np[rng.permutation(len(model_np))])
    obs, mask = pad(q[rng.permutation(len(q))].astype(np.float32))
    device = jax.devices()[0]
    on_gpu = device.platform != "cpu"
    batch = args.hypothesis_batch or (648 if on_gpu else 36)
    spec = SearchSpec(hypothesis_batch=batch)
    full = args.full_hypotheses or (spec.num_hypotheses if on_gpu else 36)
    result = {"device": str(device), "platform": device.platform, "jax": jax.__version__,
              "machine": platform.machine(), "cpus": __import__("os").cpu_count(),
              "load_average": list(__import__("os").getloadavg()),
              "model_points": int(model.shape[0]), "obs_points": int(len(q)), "obs_padded": int(obs.shape[0]),
              "spec": {k: getattr(spec, k) for k in ("num_yaws", "scale_multipliers", "top_k", "refine_other_axes",
                                                     "sweep_model_points",
                                                     "sweep_obs_points", "icp_model_points", "icp_obs_points",
                                                     "icp_iterations", "scale_iterations", "chunk",
                                                     "hypothesis_batch")}}
    def log(what):
        print(f"bench_register: {what}", file=sys.stderr, flush=True)

    if "search" not in args.skip:
        log("search")
        result["search"] = bench_search(model, obs, mask, truth, args.repeats, batch)
    if "sweep" not in args.skip:
        log("sweep")
        result["sweep"] = bench_sweep(model, obs, mask, spec, args.repeats, full)
    if "nearest" not in args.skip:
        log("nearest")
        result["nearest"] = bench_nearest(model, obs, mask, args.repeats)
    if "icp" not in args.skip:
        log("icp")
        result["icp"] = bench_icp(model, obs, mask, spec, args.repeats, args.open3d_hypotheses)
    o3d = result.get("icp", {}).get("open3d", {})
    if "hypotheses_per_s" in o3d and "search" in result:
        loop = o3d["hypotheses_per_s"]
        result["vs_open3d_loop"] = {
            "note": "the loop a user would write: Open3D point-to-point ICP per hypothesis (KD-tree built in "
                    "each registration_icp call) over the same 648 initial hypotheses, same point counts",
            "open3d_loop_hypotheses_per_s": loop,
            "ours_search_hypotheses_per_s": result["search"]["all_axes"]["hypotheses_per_s"],
            "ratio_search": round(result["search"]["all_axes"]["hypotheses_per_s"] / loop, 2),
            "ratio_icp_same_work": result["icp"]["speedup_ours_over_open3d"]}
    elif "search" in result:
        result["vs_open3d_loop"] = {"skipped": o3d.get("skipped", "icp benchmark not run")}
    emit(result, args.out)


if __name__ == "__main__":
    main()
