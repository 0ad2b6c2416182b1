"""Scripted-policy evaluation in batched MJX worlds: success rate and episodes/s, as JSON.

For every object of a converted scene that the gripper fits and the arm reaches, ``--episodes``
episodes run as that many MJX worlds at once (``interact.mjx_env.MjxPickPlace``): each world's
``reset`` moves the objects within ``--range`` of their place at a random yaw; the scripted
pick-and-place is planned on the host for each world's initial state (``robot.script``) and
its controls are stepped in all worlds together (one ``lax.scan`` of the batched ``step``:
vmapped on an accelerator, a loop over worlds inside the program on the CPU, ``over_worlds``).
Each object gets its own MJX model (its exported parts meet the finger pads, the others collide
through their hulls: ``mjx_env.mjx_model``), so the compile time is reported per object, apart.

The same episodes run in the single MuJoCo C environment (its full collision model: link
meshes, finger capsules, CoACD parts), one after another, for the reference rate measured in
the same run; ``agree`` is the fraction of episodes whose success both give alike.

    python -m experiments.robot_eval OUT_DIR [--episodes 8] [--range 0.03] [--objects 1 4] [--out result.json]
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


def _say(message: str) -> None:
    print(f"robot_eval: {message}", file=sys.stderr, flush=True)


def plans_for(env: Environment, qpos: np.ndarray, object_id: int, goal) -> tuple[np.ndarray, np.ndarray]:
    """(W, T, nu) the script's controls for each world's initial ``qpos`` (W, nq), planned in C,
    and (W,) whether a plan was found. A placement the script refuses (the hand or the carried
    object would hit another object, the target out of reach) gets one row holding the robot
    still: that episode is a failure of the scripted policy in both simulators."""
    out, planned = [], []
    for q in qpos:
        env.reset()
        env.data.qpos[:] = q
        mujoco.mj_forward(env.model, env.data)
        try:
            out.append(script.plan_pick_place(env, object_id, goal).ctrl)
            planned.append(True)
        except script.UnreachableError:
            out.append(env.data.ctrl[None].copy())
            planned.append(False)
    length = max(len(p) for p in out)
    return np.stack([np.concatenate([p, np.repeat(p[-1:], length - len(p), 0)]) for p in out]), np.array(planned)


def run_c(env: Environment, qpos: np.ndarray, plans: np.ndarray, object_id: int, goal) -> list[dict]:
    """The same episodes in the single C environment, one after another: each one's outcome."""
    body = env.object(object_id).body_id
    outcomes = []
    for q, ctrl in zip(qpos, plans):
        env.reset()
        env.data.qpos[:] = q
        mujoco.mj_forward(env.model, env.data)
        start = env.data.xmat[body].reshape(3, 3).copy()
        script.run_plan(env, script.Plan(ctrl, script.CONTROL_HZ, (), object_id, np.asarray(goal)))
        outcomes.append(script.outcome(env, object_id, goal, start))
    return outcomes


def evaluate_object(env: Environment, object_id: int, goal, episodes: int, placement_range: float, seed: int) -> dict:
    """One object's episodes in MJX worlds (its own model: its parts meet the finger pads) and in C."""
    menv = MjxPickPlace(env, object_id, goal, placement_range=placement_range)
    step = over_worlds(menv.step)

    @jax.jit
    def rollout(state, ctrl):  # ctrl (T, W, nu)
        final, _ = jax.lax.scan(lambda s, a: (step(s, a), None), state, ctrl)
        return final

    keys = jax.random.split(jax.random.PRNGKey(seed + object_id), episodes)
    _say(f"object {object_id}: compiling reset")
    t0 = time.perf_counter()
    reset = jax.jit(jax.vmap(menv.reset)).lower(keys).compile()
    reset_s = time.perf_counter() - t0
    state = jax.block_until_ready(reset(keys))
    qpos = np.asarray(state.data.qpos, np.float64)
    t0 = time.perf_counter()
    plans, planned = plans_for(env, qpos, object_id, goal)
    plan_s = time.perf_counter() - t0
    ctrl = jnp.asarray(np.swapaxes(plans, 0, 1), jnp.float32)
    _say(f"object {object_id}: compiling the rollout ({ctrl.shape[0]} ticks × {ctrl.shape[1]} worlds)")
    t0 = time.perf_counter()
    compiled = rollout.lower(state, ctrl).compile()
    rollout_s = time.perf_counter() - t0
    _say(f"object {object_id}: {episodes} episodes in MJX")
    t0 = time.perf_counter()
    final = jax.block_until_ready(compiled(state, ctrl))
    mjx_s = time.perf_counter() - t0
    _say(f"object {object_id}: the same episodes in MuJoCo C")
    t0 = time.perf_counter()
    c_outcomes = run_c(env, qpos, plans, object_id, goal)
    c_s = time.perf_counter() - t0
    mjx_wins = np.asarray(final.done) & planned
    c_wins = np.array([o["success"] for o in c_outcomes]) & planned
    steps = plans.shape[1] * menv.substeps * episodes
    return {"object": object_id, "goal": [float(v) for v in goal], "episodes": episodes,
            "ticks": int(plans.shape[1]), "substeps": menv.substeps,
            "mjx_success_rate": float(mjx_wins.mean()), "c_success_rate": float(c_wins.mean()),
            "agree": float(np.mean(mjx_wins == c_wins)), "planned": int(planned.sum()),
            "mjx_distance_m": [round(-float(r), 4) for r in np.asarray(final.reward)],
            "c_distance_m": [round(o["distance_m"], 4) for o in c_outcomes],
            "mjx_compile_s": {"reset": round(reset_s, 2), "rollout": round(rollout_s, 2)},
            "mjx_run_s": round(mjx_s, 3), "mjx_episodes_per_s": round(episodes / mjx_s, 4),
            "mjx_steps_per_s": round(steps / mjx_s, 1), "plan_s": round(plan_s, 3),
            "c_run_s": round(c_s, 3), "c_episodes_per_s": round(episodes / c_s, 4),
            "mjx_over_c": round(c_s / mjx_s, 4)}


def evaluate(out_dir: Path, episodes: int, placement_range: float, seed: int, objects: list[int] | None = None) -> dict:
    env = Environment.load(out_dir, robot=ROBOT)
    candidates = [o.id for o in env.objects if o.id is not None and o.id in env.robot.placement.reachable
                  and script.grasp_for(env, o.id).fits and (objects is None or o.id in objects)]
    if not candidates:
        raise SystemExit(f"{out_dir}: no object both fits the gripper and is within the arm's reach")
    rows = []
    for object_id in candidates:
        env.reset()
        goal = free_goal(env, object_id)
        rows.append(evaluate_object(env, object_id, goal, episodes, placement_range, seed))
    env.reset()
    total = sum(r["episodes"] for r in rows)
    return {"benchmark": "robot_eval", "scene": str(out_dir), "episodes_per_object": episodes,
            "placement_range_m": placement_range, "seed": seed,
            "objects": rows,
            "planned": sum(r["planned"] for r in rows),
            "mjx_success_rate": sum(r["mjx_success_rate"] * r["episodes"] for r in rows) / total,
            "c_success_rate": sum(r["c_success_rate"] * r["episodes"] for r in rows) / total,
            "mjx_episodes_per_s": round(total / sum(r["mjx_run_s"] for r in rows), 4),
            "c_episodes_per_s": round(total / sum(r["c_run_s"] for r in rows), 4),
            "batching": "vmap" if jax.default_backend() != "cpu" else "lax.map (over_worlds)",
            "device": jax.devices()[0].platform, "device_kind": jax.devices()[0].device_kind,
            "host_cores": os.cpu_count(), "load_average_at_end": list(os.getloadavg()),
            "jax": jax.__version__, "mujoco": mujoco.__version__, "machine": platform.platform(),
            "robot": env.robot.record()}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", type=Path, help="a `phirie convert` output folder")
    parser.add_argument("--episodes", type=int, default=8, help="episodes (= MJX worlds) per object")
    parser.add_argument("--range", type=float, default=0.03, dest="placement_range",
                        help="m: how far reset moves each object")
    parser.add_argument("--objects", type=int, nargs="*", default=None,
                        help="only these object ids (default: every one that fits and is reachable)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args(argv)
    emit(evaluate(args.out_dir, args.episodes, args.placement_range, args.seed, args.objects), args.out)


if __name__ == "__main__":
    main()
