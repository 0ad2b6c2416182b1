"""Batched worlds in MuJoCo Warp (``BatchedEnvironment(..., backend="warp")``) against MuJoCo C on
the same model, as the MJX worlds are tested: the same initial state and controls, N steps, poses
within stated tolerances; images as the single environment renders the same state."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from phirie_jax.interact.batched import BatchedEnvironment
from phirie_jax.interact.environment import Environment
from tests.interact.test_environment import box_gaussians, cameras, floor_gaussians, toy_env
from tests.interact.test_mjx_model import SCENE, box_vertices

pytest.importorskip("mujoco_warp", reason="MuJoCo Warp not installed (pip install 'phirie_jax[warp]')")

POSE_TOL = 2e-3     # m / matrix entries after 48 steps of thrown, bouncing boxes: float32 Warp vs float64 C
STATE_TOL = 2e-3    # m / rad after 40 robot steps (as the MJX worlds' test)
IMAGE_TOL = 0.01    # mean absolute rgb difference between worlds' images and single renders of the same state
SLIDE_TOL = 1e-5    # m: a pushed slider, no contact (float32 against float64)

SLIDER = """<mujoco>
  <option timestep="0.01"/>
  <worldbody>
    <body name="object_1" pos="0 0 0.05">
      <joint name="slide" type="slide" axis="1 0 0" damping="0.5"/>
      <geom type="box" size="0.03 0.03 0.03" mass="0.3" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
  <actuator><motor joint="slide" gear="1"/></actuator>
</mujoco>"""


def slider_env(tmp_path) -> Environment:
    """One actuated body, nothing in contact: both backends compile it in seconds."""
    model = mujoco.MjModel.from_xml_string(SLIDER)
    pose0 = np.eye(4)
    pose0[:3, 3] = [0.0, 0.0, 0.05]
    return Environment(tmp_path, model, floor_gaussians(), [(1, pose0, box_gaussians((0.03,) * 3, 100, 0))], cameras())


def test_warp_worlds_step_like_mujoco_c_and_render_in_one_call(tmp_path):
    from phirie_jax.interact.batched import WarpBatchedEnvironment

    env = toy_env(tmp_path)
    batch = BatchedEnvironment(env, num_worlds=3, backend="warp")
    assert isinstance(batch, WarpBatchedEnvironment)
    assert batch.mj_model is env.model and batch.collision == "parts", "the environment's own model"
    start = np.asarray(batch.placements())
    throws = np.zeros((3, env.model.nv))
    throws[1, 0:3] = [0.4, 0.0, 0.8]      # world 1: object 1 thrown
    throws[2, 6:9] = [-0.3, 0.2, 0.5]     # world 2: object 2 thrown
    batch.set_velocities(throws)
    batch.step(48)
    placements = batch.placements()
    assert isinstance(placements, jax.Array) and placements.shape == (3, 2, 4, 4)
    assert not batch.worlds.overflow().any()
    for world in range(3):
        env.reset()
        env.data.qvel[:] = throws[world]
        env.step(48)
        np.testing.assert_allclose(np.asarray(placements[world]), env.placements(), atol=POSE_TOL)
        np.testing.assert_allclose(np.asarray(batch.body_poses()[world]), env.body_poses(), atol=POSE_TOL)
    assert np.linalg.norm(placements[1, 0, :3, 3] - placements[0, 0, :3, 3]) > 0.02
    out = batch.render([0, 1])
    assert out.rgb.shape == (3, 2, 48, 64, 3)
    for world in (0, 2):
        env.reset()
        env.data.qvel[:] = throws[world]
        env.step(48)
        assert float(jnp.mean(jnp.abs(out.rgb[world, 1] - env.render(1).rgb))) < IMAGE_TOL
    batch.reset()
    np.testing.assert_allclose(np.asarray(batch.placements()), start, atol=1e-6)


def notch_env(tmp_path) -> Environment:
    """The L of two mesh boxes (``test_mjx_model.SCENE``) and a 2 cm cube dropped into its notch,
    which the L's convex hull fills: the cube rests on the lower box only when the parts collide."""
    cube = f'<mesh name="object_3_part_00" vertex="{box_vertices((-0.01, -0.01, -0.01), (0.01, 0.01, 0.01))}"/>'
    body = """<body name="object_3" pos="-0.02 0 0.09"><freejoint/>
      <inertial pos="0 0 0" mass="0.05" diaginertia="4e-6 4e-6 4e-6"/>
      <geom name="object_3_part_00" type="mesh" mesh="object_3_part_00" friction="0.7"/></body>"""
    xml = SCENE.replace("  </asset>", cube + "\n  </asset>", 1).replace("  </worldbody>", body + "\n  </worldbody>", 1)
    (tmp_path / "scene.xml").write_text(xml)
    model = mujoco.MjModel.from_xml_path(str(tmp_path / "scene.xml"))
    objects = [(k, np.eye(4), box_gaussians((0.01,) * 3, 20, k)) for k in (1, 2, 3)]
    return Environment(tmp_path, model, floor_gaussians(20), objects, [])


def test_warp_worlds_collide_through_every_part(tmp_path):
    env = notch_env(tmp_path)
    parts = BatchedEnvironment(env, num_worlds=2, backend="warp")
    hull = BatchedEnvironment(env, num_worlds=1, collision="hull", backend="warp")
    parts.step(240)
    hull.step(240)
    cube = env.model.body("object_3").id
    env.reset()
    env.step(240)
    for world in range(2):
        np.testing.assert_allclose(parts.worlds.field("xpos")[world, cube], env.data.xpos[cube], atol=POSE_TOL)
    assert abs(parts.worlds.field("xpos")[0, cube, 2] - 0.05) < 0.002, "in the notch, on the lower box"
    assert hull.worlds.field("xpos")[0, cube, 2] < 0.02, "the hull fills the notch: the cube slides off"


@pytest.mark.parametrize("backend", ["warp", "mjx"])
def test_both_backends_take_controls_and_reset_alike(tmp_path, backend):
    """The same API on both backends: per-world controls held over steps, reset, body poses."""
    env = slider_env(tmp_path)
    batch = BatchedEnvironment(env, num_worlds=3, backend=backend)
    force = np.array([[0.0], [0.5], [-1.0]])
    with pytest.raises(ValueError, match="worlds × actuators|worlds × ctrl"):
        batch.step(1, ctrl=np.zeros((2, 1)))
    batch.step(20, ctrl=force)
    batch.step(10, ctrl=jnp.asarray(2 * force, jnp.float32))
    reference = mujoco.MjData(env.model)
    for world in range(3):
        mujoco.mj_resetData(env.model, reference)
        reference.ctrl[:] = force[world]
        mujoco.mj_step(env.model, reference, nstep=20)
        reference.ctrl[:] = 2 * force[world]
        mujoco.mj_step(env.model, reference, nstep=10)
        got = np.asarray(batch.body_poses()[world, 0, :3, 3])
        np.testing.assert_allclose(got, reference.xpos[1], atol=SLIDE_TOL)
    assert float(batch.body_poses()[2, 0, 0, 3]) < -0.01 < 0.01 < float(batch.body_poses()[1, 0, 0, 3])
    batch.reset()
    np.testing.assert_allclose(np.asarray(batch.body_poses()[:, 0, :3, 3]), [[0.0, 0.0, 0.05]] * 3, atol=1e-7)


@pytest.fixture(scope="module")
def robot_env(converted):
    from phirie_jax.interact.robot.config import RobotConfig

    return Environment.load(converted[0], robot=RobotConfig(spacing=0.03))


@pytest.mark.slow  # the robot's collision and actuator kernels: about a minute of compiling on a cold Warp cache
def test_warp_worlds_with_the_robot_follow_mujoco_c(robot_env):
    from phirie_jax.interact.robot import script

    env = robot_env
    robot = env.robot
    worlds, ticks = 3, 10
    batch = BatchedEnvironment(env, num_worlds=worlds, backend="warp")
    assert batch.mj_model is env.model, "the robot's link meshes and finger capsules, the objects' own parts"
    env.reset()
    home = env.data.qpos.copy()
    np.testing.assert_allclose(batch.worlds.field("qpos"), np.repeat(home[None], worlds, 0), atol=1e-6)
    rng = np.random.default_rng(0)
    ctrl = np.repeat(env.data.ctrl[None], worlds, 0)
    ctrl[:, robot.arm_actuators] += rng.uniform(-0.3, 0.3, (worlds, len(robot.arm_actuators)))
    ctrl[:, robot.gripper_actuators] = rng.uniform(0.0, 0.04, (worlds, 1))
    substeps = script.substeps(env.timestep, script.CONTROL_HZ)
    for _ in range(ticks):
        batch.step(substeps, ctrl=ctrl)
    assert not batch.worlds.overflow().any()
    qpos = batch.worlds.field("qpos")
    poses = np.asarray(batch.body_poses())
    assert poses.shape == (worlds, len(env.objects), 4, 4) and any(o.id is None for o in env.objects)
    for w in range(worlds):
        env.reset()
        for _ in range(ticks):
            env.data.ctrl[:] = ctrl[w]
            env.step(substeps)
        assert np.abs(env.data.qpos[robot.arm_qpos] - home[robot.arm_qpos]).max() > 0.05, "the arm moved"
        np.testing.assert_allclose(qpos[w], env.data.qpos, atol=STATE_TOL)
        np.testing.assert_allclose(poses[w], env.body_poses(), atol=STATE_TOL)   # objects and links
    env.reset()


def test_a_played_control_sequence_equals_stepping_tick_by_tick(tmp_path):
    """``play`` reads each tick's controls on the device: the same worlds as ``step(ctrl=...)``."""
    from phirie_jax.interact.batched import initial_data
    from phirie_jax.interact.warp_worlds import WarpWorlds

    env = slider_env(tmp_path)
    data = initial_data(env.model)
    sequence = np.random.default_rng(1).uniform(-1.0, 1.0, (12, 3, env.model.nu))
    played = WarpWorlds(env.model, data, 3)
    played.play(sequence, 2)
    stepped = WarpWorlds(env.model, data, 3)
    for tick in sequence:
        stepped.step(2, ctrl=tick)
    np.testing.assert_array_equal(played.field("qpos"), stepped.field("qpos"))
    np.testing.assert_array_equal(played.field("ctrl"), sequence[-1].astype(np.float32))
    assert np.abs(played.field("qpos")).max() > 1e-3, "the controls moved the sliders"
    played.reset()
    played.play(sequence, 2, ticks=5)   # the first ticks only (a warm-up)
    stepped.reset()
    for tick in sequence[:5]:
        stepped.step(2, ctrl=tick)
    np.testing.assert_array_equal(played.field("qpos"), stepped.field("qpos"))


FOUR_DEVICES = """
import sys
from pathlib import Path

import jax
import numpy as np

from phirie_jax.interact.batched import BatchedEnvironment
from tests.compile_settings import compile_quickly
from tests.interact.test_environment import toy_env

compile_quickly()
assert jax.device_count() == 4
env = toy_env(Path(sys.argv[1]))
throws = np.random.default_rng(3).normal(0.0, 0.5, (6, env.model.nv))
runs = {}
for devices in (1, 4):
    batch = BatchedEnvironment(env, 6, backend="warp", devices=devices)
    assert batch.padded_worlds == (6 if devices == 1 else 8)
    batch.set_velocities(throws)
    batch.step(12)
    placements = batch.placements()
    assert placements.shape == (6, 2, 4, 4)
    runs[devices] = np.asarray(placements)
    if devices == 4:
        poses, _ = batch.worlds.poses(batch.mesh.rows)
        assert {s.device for s in poses.addressable_shards} == set(jax.devices())
np.testing.assert_array_equal(runs[4], runs[1])
assert np.abs(runs[1][1] - runs[1][0]).max() > 1e-3
print("ok")
"""


def test_warp_worlds_spread_their_poses_over_the_jax_devices(tmp_path):
    """Four JAX CPU devices (forced, in a process of its own): the Warp worlds (one CPU part) are
    padded to a multiple of them, their poses split over them, and the placements equal one device's."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=4".strip()
    done = subprocess.run([sys.executable, "-c", FOUR_DEVICES, str(tmp_path)], check=False, cwd=root,
                          capture_output=True, text=True, timeout=900,
                          env=dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu"))
    assert done.returncode == 0 and done.stdout.strip().endswith("ok"), (done.stdout + done.stderr)[-3000:]
