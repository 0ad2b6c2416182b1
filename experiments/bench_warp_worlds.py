"""World-steps/s of batched worlds in MuJoCo Warp, the MJX worlds as the baseline in the same run; prints JSON.

``--worlds`` (4,096) copies of a converted scene's reset state (``BatchedEnvironment``), every
world but world 0 with its objects thrown by a random velocity of at most ``--throw`` m/s (the
same throws on both backends), so the worlds' contacts differ:

- ``warp``: MuJoCo Warp on the scene's own model (``backend="warp"``: every CoACD part, the
  robot's full collision model with ``--robot``), CUDA graphs of ``warp_worlds.GRAPH_STEPS`` steps;
- ``mjx``: the MJX worlds on their default model (one convex hull per object, ``collision="hull"``).

Each backend's set-up (model and state put on the device), setting the throws (Warp: a forward
pass, whose kernels are compiled and loaded at their first launch) and first call (Warp: the
step's other kernels compiled and loaded, graphs captured; MJX: the program traced and compiled)
are reported apart from the median of ``--repeats`` later calls of ``--steps`` steps, which give
world-steps/s. Also: the time
to hand every world's object placements to JAX for the renderer (``placements``; on the device,
no host round trip), and world 0 (at rest) against MuJoCo C on the same model after the same
steps (largest body position difference).

    python -m experiments.bench_warp_worlds OUT_DIR [--worlds 4096] [--steps 240] [--repeats 3]
        [--backends warp mjx] [--robot] [--contacts C] [--constraints R] [--out result.json]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np


def _say(message: str) -> None:
    print(f"bench_warp_worlds: {message}", file=sys.stderr, flush=True)


def throws(env, worlds: int, speed: float, seed: int = 0) -> np.ndarray:
    """(worlds, nv) velocities: each object's free joint a random linear velocity of at most
    ``speed`` (m/s, pointing up), world 0 left at rest."""
    model = env.model
    rng = np.random.default_rng(seed)
    qvel = np.zeros((worlds, model.nv))
    for o in env.objects:
        if o.id is None:
            continue
        dof = int(model.jnt_dofadr[model.body_jntadr[o.body_id]])
        direction = rng.normal(size=(worlds, 3))
        direction[:, 2] = np.abs(direction[:, 2])
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        qvel[:, dof:dof + 3] = direction * speed * rng.uniform(0.0, 1.0, (worlds, 1))
    qvel[0] = 0.0
    return qvel


def bench_backend(env, backend: str, worlds: int, steps: int, repeats: int, speed: float,
                  capacities: dict | None = None) -> dict:
    import jax
    import mujoco

    from phirie_jax.interact.batched import BatchedEnvironment, initial_data

    _say(f"{backend}: putting {worlds} worlds on the device")
    t0 = time.perf_counter()
    batch = BatchedEnvironment(env, worlds, backend=backend, **(capacities if backend == "warp" else {}))
    setup_s = time.perf_counter() - t0

    def wait():
        if backend == "warp":
            batch.worlds.synchronize()
        else:
            jax.block_until_ready(batch.data.qpos)

    t0 = time.perf_counter()
    batch.set_velocities(throws(env, worlds, speed))
    wait()
    set_velocities_s = time.perf_counter() - t0
    times = []
    for call in range(1 + repeats):
        _say(f"{backend}: call {call + 1} of {1 + repeats} ({steps} steps)")
        t0 = time.perf_counter()
        batch.step(steps)
        wait()
        times.append(time.perf_counter() - t0)
    run_s = statistics.median(times[1:])
    t0 = time.perf_counter()
    jax.block_until_ready(batch.placements())
    first_placements_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    placements = jax.block_until_ready(batch.placements())
    placements_s = time.perf_counter() - t0
    # world 0 (at rest) against MuJoCo C on the same model, stepped as often
    reference = initial_data(batch.mj_model, env.robot)
    mujoco.mj_step(batch.mj_model, reference, nstep=steps * (1 + repeats))
    ids = [o.body_id for o in env.objects]
    got = np.asarray(batch.body_poses()[0, :, :3, 3], np.float64)
    colliding = (batch.mj_model.geom_contype | batch.mj_model.geom_conaffinity) > 0
    row = {"backend": backend, "collision": batch.collision, "colliding_geoms": int(colliding.sum()),
           "setup_s": round(setup_s, 2), "set_velocities_s": round(set_velocities_s, 2),
           "first_call_s": round(times[0], 2),
           ("compile_capture_s" if backend == "warp" else "compile_s"): round(times[0] - run_s, 2),
           "run_s": round(run_s, 4), "world_steps_per_s": round(worlds * steps / run_s, 1),
           "placements_first_s": round(first_placements_s, 3), "placements_ms": round(1e3 * placements_s, 3),
           "placements_shape": list(placements.shape),
           "world0_vs_c_max_position_m": float(np.abs(got - reference.xpos[ids]).max())}
    if backend == "warp":
        row.update({"overflow_worlds": int(batch.worlds.overflow()[:worlds].sum()),
                    "contacts_per_world": batch.worlds.contacts, "constraints_per_world": batch.worlds.constraints,
                    "warp_devices": list(batch.worlds.devices)})
    return row


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", type=Path, help="a `phirie convert` output folder (the demo's: out/demo/convert)")
    parser.add_argument("--worlds", type=int, default=4096)
    parser.add_argument("--steps", type=int, default=240, help="simulator steps per timed call")
    parser.add_argument("--repeats", type=int, default=3, help="timed calls after the first")
    parser.add_argument("--throw", type=float, default=0.5, help="m/s: the largest random throw of an object")
    parser.add_argument("--backends", nargs="+", choices=["warp", "mjx"], default=["warp", "mjx"])
    parser.add_argument("--robot", action="store_true", help="the Franka Panda in every world")
    parser.add_argument("--contacts", type=int, default=None,
                        help="Warp: contacts allocated per world (default: warp_worlds.capacity)")
    parser.add_argument("--constraints", type=int, default=None,
                        help="Warp: constraint rows allocated per world (default: warp_worlds.capacity)")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args(argv)
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")   # MuJoCo Warp shares the device with JAX

    import jax
    import mujoco

    from experiments.report import emit
    from phirie_jax.interact.environment import Environment

    robot = None
    if args.robot:
        from phirie_jax.interact.robot.config import RobotConfig

        robot = RobotConfig(spacing=0.03)
    env = Environment.load(args.out_dir, robot=robot)
    result = {"benchmark": "bench_warp_worlds", "scene": str(args.out_dir), "worlds": args.worlds,
              "steps": args.steps, "repeats": args.repeats, "throw_m_s": args.throw, "robot": args.robot,
              "objects": sum(o.id is not None for o in env.objects), "timestep": env.timestep,
              "device": str(jax.devices()[0]), "device_kind": jax.devices()[0].device_kind,
              "jax": jax.__version__, "mujoco": mujoco.__version__, "machine": platform.platform(),
              "host_cores": os.cpu_count()}
    if "warp" in args.backends:
        from importlib.metadata import version

        import warp as wp

        wp.init()
        cache = Path(wp.config.kernel_cache_dir)   # a warm cache makes the first call load, not compile
        result.update({"warp_version": version("warp-lang"), "mujoco_warp_version": version("mujoco-warp"),
                       "warp_cached_modules_at_start": len(list(cache.iterdir())) if cache.is_dir() else 0})
    for backend in args.backends:
        result[backend] = bench_backend(env, backend, args.worlds, args.steps, args.repeats, args.throw,
                                        {"contacts": args.contacts, "constraints": args.constraints})
        _say(f"{backend}: {result[backend]['world_steps_per_s']:.0f} world-steps/s")
    if "warp" in result and "mjx" in result:
        result["warp_over_mjx"] = round(result["warp"]["world_steps_per_s"] / result["mjx"]["world_steps_per_s"], 3)
    result["load_average_at_end"] = list(os.getloadavg())
    emit(result, args.out)


if __name__ == "__main__":
    main()
