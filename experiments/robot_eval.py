"""Scripted-policy evaluation in batched worlds (MJX or MuJoCo Warp): success rate and episodes/s, as JSON.

For every object of a converted scene that the gripper fits and the arm reaches, ``--episodes``
episodes run as that many worlds at once: each world's placement is drawn by the MJX
environment's ``reset`` (``interact.mjx_env.MjxPickPlace``: the objects within ``--range`` of
their place at a random yaw; the same seed gives the same placements on either backend); the
scripted pick-and-place is planned on the host for each world's initial state
(``robot.script``) and its controls are stepped in all worlds together.

``--backend mjx`` (default): one ``lax.scan`` of the batched ``step`` (vmapped on an
accelerator, a loop over worlds inside the program on the CPU, ``over_worlds``). Each object gets
its own MJX model (its exported parts meet the finger pads, the others collide through their
hulls: ``mjx_env.mjx_model``), so the compile time is reported per object, apart.

``--backend warp``: the worlds run the scene's own MuJoCo model (every CoACD part, the robot's
link meshes and finger capsules) in MuJoCo Warp (``interact.warp_worlds``): the control
sequences are put on the device once and read tick by tick there (CUDA graphs on a GPU); a
warm-up of a few ticks compiles the kernels and captures the graphs, reported apart from the
run. An episode's success is MuJoCo C's rule (``script.outcome``) on the world's final state.

The same episodes run in the single MuJoCo C environment (its full collision model), one after
another (or over ``--workers`` processes, which also plan), for the reference rate measured in
the same run; ``agree`` is the fraction of episodes whose success both give alike.

    python -m experiments.robot_eval OUT_DIR [--backend mjx|warp] [--episodes 8] [--range 0.03]
        [--objects 1 4] [--workers 1] [--out result.json]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from experiments.report import emit
from phirie_jax.interact.environment import Environment
from phirie_jax.interact.mjx_env import MjxPickPlace, over_worlds
from phirie_jax.interact.robot import script
from phirie_jax.interact.robot.config import RobotConfig
from phirie_jax.interact.rollout import free_goal

ROBOT = RobotConfig(spacing=0.03)   # no images are rendered: the Gaussians only need to exist
_ENV: Environment | None = None     # a worker process's own environment (``_start_worker``)


def _say(message: str) -> None:
    print(f"robot_eval: {message}", file=sys.stderr, flush=True)


def _start_worker(out_dir: Path) -> None:
    """A worker process: JAX kept on the CPU (the accelerator is the parent's), its own environment."""
    global _ENV
    jax.config.update("jax_platforms", "cpu")
    _ENV = Environment.load(out_dir, robot=ROBOT)


def _placed(env: Environment, q: np.ndarray) -> None:
    env.reset()
    env.data.qpos[:] = q
    mujoco.mj_forward(env.model, env.data)


def plan_one(env: Environment, q: np.ndarray, object_id: int, goal) -> np.ndarray | None:
    """(T, nu) the script's controls from the initial ``qpos`` q, planned in C; None when the script
    refuses the placement (the hand or the carried object would hit another object, the target
    out of reach)."""
    _placed(env, q)
    try:
        return script.plan_pick_place(env, object_id, goal).ctrl
    except script.UnreachableError:
        return None


def run_c_one(env: Environment, q: np.ndarray, ctrl: np.ndarray, object_id: int, goal) -> dict:
    """One episode in the single C environment from ``q`` under ``ctrl`` (T, nu): its outcome."""
    _placed(env, q)
    start = env.data.xmat[env.object(object_id).body_id].reshape(3, 3).copy()
    script.run_plan(env, script.Plan(ctrl, script.CONTROL_HZ, (), object_id, np.asarray(goal)))
    return script.outcome(env, object_id, goal, start)


def _plan_task(args):
    return plan_one(_ENV, *args)


def _c_task(args):
    return run_c_one(_ENV, *args)


class Host:
    """Where the plans and the C episodes run: this process, or ``workers`` processes (spawned,
    each loading the scene once)."""

    def __init__(self, env: Environment, out_dir: Path, workers: int = 1):
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        self.env, self.workers = env, max(1, int(workers))
        self.pool = (ProcessPoolExecutor(self.workers, multiprocessing.get_context("spawn"),
                                         initializer=_start_worker, initargs=(out_dir,))
                     if self.workers > 1 else None)

    def map(self, one, task, items: list[tuple]) -> list:
        if self.pool is None:
            return [one(self.env, *item) for item in items]
        return list(self.pool.map(task, items, chunksize=max(1, len(items) // (4 * self.workers))))

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown()


def plans_for(host: Host, qpos: np.ndarray, object_id: int, goal) -> tuple[np.ndarray, np.ndarray]:
    """(W, T, nu) the script's controls for each world's initial ``qpos`` (W, nq) and (W,) whether
    a plan was found. A refused placement (``plan_one``) gets one row holding the robot still:
    that episode is a failure of the scripted policy in both simulators."""
    out = host.map(plan_one, _plan_task, [(q, object_id, goal) for q in qpos])
    planned = np.array([p is not None for p in out])
    host.env.reset()
    still = host.env.data.ctrl[None].copy()
    out = [still if p is None else p for p in out]
    length = max(len(p) for p in out)
    return np.stack([np.concatenate([p, np.repeat(p[-1:], length - len(p), 0)]) for p in out]), planned


def run_c(host: Host, qpos: np.ndarray, plans: np.ndarray, object_id: int, goal) -> list[dict]:
    """The same episodes in the single C environment: each one's outcome."""
    return host.map(run_c_one, _c_task, [(q, ctrl, object_id, goal) for q, ctrl in zip(qpos, plans)])


def rollout_mjx(env: Environment, menv: MjxPickPlace, state, plans: np.ndarray, object_id: int, goal) -> dict:
    """The episodes in MJX worlds from the reset ``state``: success, distance, compile and run times."""
    step = over_worlds(menv.step)

    @jax.jit
    def rollout(state, ctrl):  # ctrl (T, W, nu)
        final, _ = jax.lax.scan(lambda s, a: (step(s, a), None), state, ctrl)
        return final

    ctrl = jnp.asarray(np.swapaxes(plans, 0, 1), jnp.float32)
    _say(f"object {object_id}: compiling the rollout ({ctrl.shape[0]} ticks × {ctrl.shape[1]} worlds)")
    t0 = time.perf_counter()
    compiled = rollout.lower(state, ctrl).compile()
    compile_s = time.perf_counter() - t0
    _say(f"object {object_id}: {ctrl.shape[1]} episodes in MJX")
    t0 = time.perf_counter()
    final = jax.block_until_ready(compiled(state, ctrl))
    run_s = time.perf_counter() - t0
    return {"success": np.asarray(final.done), "distance": -np.asarray(final.reward, np.float64),
            "compile_s": {"rollout": round(compile_s, 2)}, "run_s": run_s}


def rollout_warp(env: Environment, qpos: np.ndarray, plans: np.ndarray, substeps: int, object_id: int,
                 goal) -> dict:
    """The episodes in MuJoCo Warp worlds of the scene's own model from ``qpos`` (W, nq): success
    and distance by MuJoCo C's rule on each final state, set-up, warm-up and run times."""
    from phirie_jax.interact.batched import initial_data
    from phirie_jax.interact.warp_worlds import GRAPH_TICKS, WarpWorlds

    episodes = len(qpos)
    ctrl = np.ascontiguousarray(np.swapaxes(plans, 0, 1), np.float32)   # (T, W, nu)
    t0 = time.perf_counter()
    worlds = WarpWorlds(env.model, initial_data(env.model, env.robot), episodes, grasp=True)
    put_s = time.perf_counter() - t0
    _say(f"object {object_id}: compiling and capturing ({GRAPH_TICKS + 1} ticks × {episodes} worlds on "
         f"{','.join(worlds.devices)})")
    t0 = time.perf_counter()
    worlds.reset()   # the timed run's every kernel is compiled here (reset's too), its graphs captured
    worlds.set_state(qpos=qpos)
    worlds.play(ctrl, substeps, ticks=GRAPH_TICKS + 1)
    worlds.synchronize()
    warmup_s = time.perf_counter() - t0
    _say(f"object {object_id}: {episodes} episodes in MuJoCo Warp")
    t0 = time.perf_counter()
    worlds.reset()
    worlds.set_state(qpos=qpos)
    worlds.play(ctrl, substeps)
    final = worlds.field("qpos")
    run_s = time.perf_counter() - t0
    outcomes = []
    for q0, q in zip(qpos, final):
        _placed(env, q0)
        start = env.data.xmat[env.object(object_id).body_id].reshape(3, 3).copy()
        _placed(env, q)
        outcomes.append(script.outcome(env, object_id, goal, start))
    env.reset()
    return {"success": np.array([o["success"] for o in outcomes]),
            "distance": np.array([o["distance_m"] for o in outcomes]),
            "compile_s": {"put_model": round(put_s, 2), "warmup": round(warmup_s, 2)}, "run_s": run_s,
            "overflow_worlds": int(worlds.overflow().sum()), "contacts_per_world": worlds.contacts,
            "constraints_per_world": worlds.constraints, "devices": list(worlds.devices)}


def evaluate_object(env: Environment, host: Host, object_id: int, goal, episodes: int, placement_range: float,
                    seed: int, backend: str = "mjx") -> dict:
    """One object's episodes in batched worlds of ``backend`` and in C, from the same placements."""
    menv = MjxPickPlace(env, object_id, goal, placement_range=placement_range)
    keys = jax.random.split(jax.random.PRNGKey(seed + object_id), episodes)
    _say(f"object {object_id}: compiling reset")
    t0 = time.perf_counter()
    reset = jax.jit(jax.vmap(menv.reset)).lower(keys).compile()
    reset_s = time.perf_counter() - t0
    state = jax.block_until_ready(reset(keys))
    qpos = np.asarray(state.data.qpos, np.float64)
    t0 = time.perf_counter()
    plans, planned = plans_for(host, qpos, object_id, goal)
    plan_s = time.perf_counter() - t0
    if backend == "warp":
        run = rollout_warp(env, qpos, plans, menv.substeps, object_id, goal)
    else:
        run = rollout_mjx(env, menv, state, plans, object_id, goal)
    _say(f"object {object_id}: the same episodes in MuJoCo C")
    t0 = time.perf_counter()
    c_outcomes = run_c(host, qpos, plans, object_id, goal)
    c_s = time.perf_counter() - t0
    wins = run["success"] & planned
    c_wins = np.array([o["success"] for o in c_outcomes]) & planned
    steps = plans.shape[1] * menv.substeps * episodes
    b = backend
    extra = {k: v for k, v in run.items() if k not in ("success", "distance", "compile_s", "run_s")}
    return {"object": object_id, "goal": [float(v) for v in goal], "episodes": episodes,
            "ticks": int(plans.shape[1]), "substeps": menv.substeps,
            f"{b}_success_rate": float(wins.mean()), "c_success_rate": float(c_wins.mean()),
            "agree": float(np.mean(wins == c_wins)), "planned": int(planned.sum()),
            f"{b}_distance_m": [round(float(d), 4) for d in run["distance"]],
            "c_distance_m": [round(o["distance_m"], 4) for o in c_outcomes],
            f"{b}_compile_s": {"reset": round(reset_s, 2), **run["compile_s"]},
            f"{b}_run_s": round(run["run_s"], 3), f"{b}_episodes_per_s": round(episodes / run["run_s"], 4),
            f"{b}_steps_per_s": round(steps / run["run_s"], 1), "plan_s": round(plan_s, 3),
            "c_run_s": round(c_s, 3), "c_episodes_per_s": round(episodes / c_s, 4),
            f"{b}_over_c": round(c_s / run["run_s"], 4), **{f"{b}_{k}": v for k, v in extra.items()}}


def evaluate(out_dir: Path, episodes: int, placement_range: float, seed: int, objects: list[int] | None = None,
             backend: str = "mjx", workers: int = 1) -> dict:
    warp = _warp_versions() if backend == "warp" else {}
    env = Environment.load(out_dir, robot=ROBOT)
    candidates = [o.id for o in env.objects if o.id is not None and o.id in env.robot.placement.reachable
                  and script.grasp_for(env, o.id).fits and (objects is None or o.id in objects)]
    if not candidates:
        raise SystemExit(f"{out_dir}: no object both fits the gripper and is within the arm's reach")
    host = Host(env, out_dir, workers)
    rows = []
    try:
        for object_id in candidates:
            env.reset()
            goal = free_goal(env, object_id)
            rows.append(evaluate_object(env, host, object_id, goal, episodes, placement_range, seed, backend))
    finally:
        host.close()
    env.reset()
    total = sum(r["episodes"] for r in rows)
    b = backend
    batching = ({"mjx": "vmap" if jax.default_backend() != "cpu" else "lax.map (over_worlds)",
                 "warp": "MuJoCo Warp, one Data of N worlds" + (" (CUDA graphs)" if jax.default_backend() == "gpu"
                                                                else "")})[b]
    return {"benchmark": "robot_eval", "backend": b, "scene": str(out_dir), "episodes_per_object": episodes,
            "placement_range_m": placement_range, "seed": seed,
            "objects": rows,
            "planned": sum(r["planned"] for r in rows),
            f"{b}_success_rate": sum(r[f"{b}_success_rate"] * r["episodes"] for r in rows) / total,
            "c_success_rate": sum(r["c_success_rate"] * r["episodes"] for r in rows) / total,
            "agree": sum(r["agree"] * r["episodes"] for r in rows) / total,
            f"{b}_episodes_per_s": round(total / sum(r[f"{b}_run_s"] for r in rows), 4),
            "c_episodes_per_s": round(total / sum(r["c_run_s"] for r in rows), 4),
            "c_workers": host.workers, "batching": batching,
            "device": jax.devices()[0].platform, "device_kind": jax.devices()[0].device_kind,
            "host_cores": os.cpu_count(), "load_average_at_end": list(os.getloadavg()),
            "jax": jax.__version__, "mujoco": mujoco.__version__, "machine": platform.platform(),
            **warp, "robot": env.robot.record()}


def _warp_versions() -> dict:
    """Warp's versions and how many compiled modules its kernel cache held (a warm cache makes the
    warm-up load kernels, not compile them)."""
    from importlib.metadata import version

    import warp as wp

    wp.init()
    cache = Path(wp.config.kernel_cache_dir)
    return {"warp_version": version("warp-lang"), "mujoco_warp_version": version("mujoco-warp"),
            "warp_cached_modules_at_start": len(list(cache.iterdir())) if cache.is_dir() else 0}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", type=Path, help="a `phirie convert` output folder")
    parser.add_argument("--backend", choices=["mjx", "warp"], default="mjx", help="the batched worlds' simulator")
    parser.add_argument("--episodes", type=int, default=8, help="episodes (= worlds) per object")
    parser.add_argument("--range", type=float, default=0.03, dest="placement_range",
                        help="m: how far reset moves each object")
    parser.add_argument("--objects", type=int, nargs="*", default=None,
                        help="only these object ids (default: every one that fits and is reachable)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=1,
                        help="processes that plan and run the MuJoCo C episodes (default: this one)")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args(argv)
    if args.backend == "warp":   # JAX allocates as it goes: MuJoCo Warp shares the device
        os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    emit(evaluate(args.out_dir, args.episodes, args.placement_range, args.seed, args.objects, args.backend,
                  args.workers), args.out)


if __name__ == "__main__":
    main()
