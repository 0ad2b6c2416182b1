"""The Gymnasium environment: the checker passes, resets randomize collision-free and reproducibly,
and joint-target actions drive the robot (the scripted plan succeeds through them)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from phirie_jax.interact.gym_env import GymConfig, PickPlaceEnv
from phirie_jax.interact.robot import script
from phirie_jax.interact.robot.config import RobotConfig

LIGHT = RobotConfig(spacing=0.03)


def test_the_gymnasium_checker_passes(converted):
    from gymnasium.utils.env_checker import check_env

    env = PickPlaceEnv(converted[0], GymConfig(robot=LIGHT, depth=True, width=32))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the checker's notes on unbounded boxes and on make()
        check_env(env, skip_render_check=False)
    obs, _ = env.reset(seed=0)
    assert obs["rgb"]["wrist"].shape == (24, 32, 3) and obs["depth"]["0"].dtype == np.float32
    assert obs["rgb"]["0"].std() > 5, "the scene camera sees the scene"


@pytest.fixture(scope="module")
def blind(converted):
    """No cameras: physics and the action mapping only."""
    return PickPlaceEnv(converted[0], GymConfig(robot=LIGHT, cameras=(), control_hz=60.0, max_steps=1000,
                                                placement_range=0.04))


def test_resets_move_objects_apart_on_the_support_reproducibly(blind):
    first, _ = blind.reset(seed=5)
    again, _ = blind.reset(seed=5)
    other, _ = blind.reset(seed=6)
    np.testing.assert_array_equal(first["object_poses"], again["object_poses"])
    assert np.abs(first["object_poses"] - other["object_poses"]).max() > 1e-3
    for seed in range(8):
        obs, _ = blind.reset(seed=seed)
        xy = obs["object_poses"][:, :2]
        start = np.array([blind.home_pose[k][:2, 3] for k in range(len(xy))])
        assert np.all(np.abs(xy - start) <= 0.04 + 0.12), "moved within range (pose origin vs centre)"
        gaps = [np.linalg.norm(xy[i] - xy[j]) for i in range(len(xy)) for j in range(i)]
        assert min(gaps) > 0.08
        blind.env.step(120)  # collision-free and supported: nothing falls or jumps
        z = blind.env.data.xpos[[blind.env.object(i).body_id for i in blind.object_ids], 2]
        np.testing.assert_allclose(z, obs["object_poses"][:, 2], atol=2e-3)


def test_the_scripted_plan_succeeds_through_joint_actions(blind):
    blind.reset(seed=1)
    env = blind.env
    plan = script.plan_pick_place(env, blind.object_id, blind.goal)
    robot = env.robot
    arm = env.model.actuator_ctrlrange[robot.arm_actuators]
    done = False
    for ctrl in plan.ctrl:
        arm_action = 2 * (ctrl[robot.arm_actuators] - arm[:, 0]) / (arm[:, 1] - arm[:, 0]) - 1
        closed = ctrl[robot.gripper_actuators[0]] < 0.5 * (robot.gripper_open[0] + robot.gripper_closed[0])
        _, reward, done, _, info = blind.step(np.append(arm_action, 1.0 if closed else -1.0))
    assert done and info["success"] and reward > -0.03, info
