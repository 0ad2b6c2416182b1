"""Scripted-policy evaluation in batched MJX worlds: success rate and episodes/s, as JSON.

For every object of a converted scene that the gripper fits and the arm reaches, ``--episodes``
episodes run as that many MJX worlds at once (``interact.mjx_env.MjxPickPlace``): each world's
``reset`` moves the objects within ``--range`` of their place at a random yaw; the scripted
pick-and-place is planned on the host for each world's initial state (``robot.script``) and
its controls are stepped in all worlds together (one ``lax.scan`` of the vmapped ``step``).
The same episodes run in the single MuJoCo C environment, one after another, for the reference
rate measured in the same run. Compile time (the first batch's call) is reported apart.

    python -m experiments.robot_eval OUT_DIR [--episodes 8] [--range 0.03] [--out result.json]
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from experiments.report import emit
from phirie_jax.interact.environment import Environment
from phirie_jax.interact.mjx_env import MjxPickPlace
from phirie_jax.interact.robot import script
from phirie_jax.interact.robot.config import RobotConfig
from phirie_jax.interact.rollout import free_goal

ROBOT = RobotConfig(spacing=0.03)   # no images are rendered: the Gaussians only need to exist


def plans_for(env: Environment, menv: MjxPickPlace, qpos: np.ndarray, object_id: int, goal) -> np.ndarray:
    """(W, T, nu) the script's controls for each world's initial ``qpos`` (W, nq), planned in C."""
    out = []
    for q in qpos:
        env.reset()
        env.data.qpos[:] = q
        mujoco.mj_forward(env.model, env.data)
        out.append(script.plan_pick_place(env, object_id, goal).ctrl)
    length = max(len(p) for p in out)
    return np.stack([np.concatenate([p, np.repeat(p[-1:], length - len(p), 0)]) for p in out])


def run_c(env: Environment, qpos: np.ndarray, plans: np.ndarray, object_id: int, goal) -> list[bool]:
    """The same episodes in the single C environment, one after another."""
    body = env.object(object_id).body_id
    wins = []
    for q, ctrl in zip(qpos, plans):
        env.reset()
        env.data.qpos[:] = q
        mujoco.mj_forward(env.model, env.data)
        start = env.data.xmat[body].reshape(3, 3).copy()
        plan = script.Plan(ctrl, script.CONTROL_HZ, (), object_id, np.asarray(goal))
        script.run_plan(env, plan)
        wins.append(script.outcome(env, object_id, goal, start)["success"])
    return wins


def evaluate(out_dir: Path, episodes: int, placement_range: float, seed: int) -> dict:
    env = Environment.load(out_dir, robot=ROBOT)
    candidates = [o.id for o in env.objects if o.id is not None and o.id in env.robot.placement.reachable
                  and script.grasp_for(env, o.id).fits]
    rows = []
    for object_id in candidates:
        env.reset()
        goal = free_goal(env, object_id)
        menv = MjxPickPlace(env, object_id, goal, placement_range=placement_range)
        reset = jax.jit(jax.vmap(menv.reset))

        @jax.jit
        def rollout(state, ctrl):  # ctrl (T, W, nu)
            final, _ = jax.lax.scan(lambda s, a: (jax.vmap(menv.step)(s, a), None), state, ctrl)
            return final

        keys = jax.random.split(jax.random.PRNGKey(seed + object_id), episodes)
        t0 = time.perf_counter()
        state = jax.block_until_ready(reset(keys))
        reset_first = time.perf_counter() - t0
        qpos = np.asarray(state.data.qpos, np.float64)
        t0 = time.perf_counter()
        plans = plans_for(env, menv, qpos, object_id, goal)
        plan_s = time.perf_counter() - t0
        ctrl = jnp.asarray(np.swapaxes(plans, 0, 1), jnp.float32)
        t0 = time.perf_counter()
        compiled = rollout.lower(state, ctrl).compile()
        compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        final = jax.block_until_ready(compiled(state, ctrl))
        mjx_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        c_wins = run_c(env, qpos, plans, object_id, goal)
        c_s = time.perf_counter() - t0
        mjx_wins = np.asarray(final.done)
        rows.append({"object": object_id, "goal": [float(v) for v in goal], "episodes": episodes,
                     "ticks": int(plans.shape[1]), "substeps": menv.substeps,
                     "mjx_success_rate": float(mjx_wins.mean()), "c_success_rate": float(np.mean(c_wins)),
                     "agree": float(np.mean(mjx_wins == np.asarray(c_wins))),
                     "mjx_compile_s": round(compile_s + reset_first, 2), "mjx_run_s": round(mjx_s, 3),
                     "mjx_episodes_per_s": round(episodes / mjx_s, 3), "plan_s": round(plan_s, 3),
                     "c_run_s": round(c_s, 3), "c_episodes_per_s": round(episodes / c_s, 3),
                     "mjx_over_c": round(c_s / mjx_s, 3)})
    total = sum(r["episodes"] for r in rows)
    return {"benchmark": "robot_eval", "scene": str(out_dir), "episodes_per_object": episodes,
            "placement_range_m": placement_range, "objects": rows,
            "success_rate": (sum(r["mjx_success_rate"] * r["episodes"] for r in rows) / total) if total else None,
            "device": jax.devices()[0].platform, "jax": jax.__version__, "machine": platform.platform(),
            "robot": env.robot.record()}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", type=Path, help="a `phirie convert` output folder")
    parser.add_argument("--episodes", type=int, default=8, help="episodes (= MJX worlds) per object")
    parser.add_argument("--range", type=float, default=0.03, dest="placement_range",
                        help="m: how far reset moves each object")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args(argv)
    emit(evaluate(args.out_dir, args.episodes, args.placement_range, args.seed), args.out)


if __name__ == "__main__":
    main()
