"""The functional MJX environment: 8 worlds stepped by one jitted, vmapped program equal the
single MuJoCo C environment for the same actions, and their images its renders.

Slow: MJX compiles the robot-and-objects model's step for minutes on a 2-core CPU."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from phirie_jax.interact.environment import Environment
from phirie_jax.interact.mjx_env import MjxPickPlace
from phirie_jax.interact.robot.config import RobotConfig

pytestmark = pytest.mark.slow

WORLDS, TICKS = 8, 30
STATE_TOL = 2e-3      # m / rad after 0.5 s: MJX in float32 against MuJoCo C in float64
IMAGE_TOL = 0.02      # mean absolute rgb difference of the same state rendered in and out of jit


def test_eight_worlds_match_the_single_c_environment(converted):
    env = Environment.load(converted[0], robot=RobotConfig(spacing=0.03))
    menv = MjxPickPlace(env, 1, (-0.2, 0.06), cameras=(0, "wrist"), width=32, collision="parts")
    states = jax.jit(jax.vmap(menv.reset))(jax.random.split(jax.random.PRNGKey(0), WORLDS))
    qpos0 = np.asarray(states.data.qpos, np.float64)
    assert np.abs(qpos0[0] - qpos0[1]).max() > 1e-3, "resets differ per world"
    robot = env.robot
    rng = np.random.default_rng(0)
    actions = np.repeat(np.asarray(env.data.ctrl)[None, None], WORLDS, 0).repeat(TICKS, 1)
    actions[..., robot.arm_actuators] += rng.uniform(-0.3, 0.3, (WORLDS, 1, len(robot.arm_actuators)))
    actions[..., robot.gripper_actuators] = rng.uniform(0.0, 0.04, (WORLDS, 1, 1))
    step = jax.jit(jax.vmap(menv.step))
    for t in range(TICKS):
        states = step(states, jnp.asarray(actions[:, t], jnp.float32))
    assert not bool(np.any(states.info["render_overflow"]))
    for w in range(WORLDS):
        env.reset()
        env.data.qpos[:] = qpos0[w]
        mujoco.mj_forward(env.model, env.data)
        for t in range(TICKS):
            env.data.ctrl[:] = actions[w, t]
            env.step(menv.substeps)
        np.testing.assert_allclose(np.asarray(states.data.qpos[w]), env.data.qpos, atol=STATE_TOL)
        np.testing.assert_allclose(np.asarray(states.obs["object_poses"][w])[:, :3],
                                   env.data.xpos[menv.object_bodies], atol=STATE_TOL)
        images = np.asarray(states.obs["rgb"][w])
        assert images.shape == (2, 24, 32, 3)
        for k, camera in enumerate((0, "wrist")):
            cam = env.camera(camera)
            single = np.asarray(env.render(cam.scaled(32 / cam.width), background=(0.62, 0.66, 0.72)).rgb)
            assert np.abs(images[k] - single).mean() < IMAGE_TOL
