"""The functional MJX environment: its model collides through finger pads and object hulls; 8
worlds reset and stepped by jitted, batched programs equal MuJoCo C on the same model for the
same actions, and their images the single environment's renders of the same states.

The stepping test is slow: MJX compiles the robot-and-objects step for about a minute of CPU."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from phirie_jax.interact.environment import Environment
from phirie_jax.interact.mjx_env import MjxPickPlace, mjx_model, over_worlds
from phirie_jax.interact.mjx_model import hull_collision_spec
from phirie_jax.interact.robot import script
from phirie_jax.interact.robot.collision import PAD_SUFFIX, colliding_geoms, finger_bodies, grip_parts_spec
from phirie_jax.interact.robot.config import RobotConfig

WORLDS, TICKS = 8, 15
STATE_TOL = 2e-3      # m / rad after 0.25 s: MJX in float32 against MuJoCo C in float64
TURN_TOL = 0.01       # rad between an object's orientations (a fruit rocks on its 32-vertex hull)
IMAGE_TOL = 0.02      # mean absolute rgb difference of the same state rendered in and out of jit
BOX_TOL = 1e-9        # m: a pad against the points of its finger's capsules
PAD_TIGHT = 2e-4      # m: the capsules' sampled points come this close to the pad's faces
BACKGROUND = (0.62, 0.66, 0.72)


@pytest.fixture(scope="module")
def env(converted):
    return Environment.load(converted[0], robot=RobotConfig(spacing=0.03))


def test_the_mjx_model_collides_through_finger_pads_and_object_hulls(env):
    model = mjx_model(env)
    robot = env.robot
    colliding = lambda m, bodies: [g for b in bodies for g in colliding_geoms(m, b)]  # noqa: E731
    fingers = finger_bodies(model, robot)
    assert len(fingers) == 2
    pads = colliding(model, robot.bodies)
    assert sorted(model.geom(g).name for g in pads) == sorted(model.body(b).name + PAD_SUFFIX for b in fingers)
    for g in pads:
        assert model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX and model.geom_condim[g] == 3
        body = int(model.geom_bodyid[g])
        points = np.concatenate([_capsule_surface(env.model, c) for c in colliding_geoms(env.model, body)
                                 if env.model.geom_type[c] == mujoco.mjtGeom.mjGEOM_CAPSULE])
        low, high = model.geom_pos[g] - model.geom_size[g], model.geom_pos[g] + model.geom_size[g]
        assert np.all(points >= low - BOX_TOL) and np.all(points <= high + BOX_TOL), "the pad holds the capsules"
        # and no more: the capsules reach the pad's inner face and its tip (the grip, the support)
        inner = np.argmax(np.abs(model.geom_pos[g][:2]))  # the finger's offset from the hand's axis
        side = low[inner] if model.geom_pos[g][inner] > 0 else high[inner]
        assert np.min(np.abs(points[:, inner] - side)) < PAD_TIGHT
        assert high[2] - points[:, 2].max() < PAD_TIGHT
    for o in env.objects:
        if o.id is not None:
            assert len(colliding_geoms(model, o.body_id)) == 1
    # the same bodies, joints, actuators and inertia: MuJoCo C runs this model as a reference
    for field in ("body_mass", "body_inertia", "body_ipos", "jnt_range", "dof_damping", "actuator_gainprm"):
        np.testing.assert_array_equal(getattr(model, field), getattr(env.model, field))
    assert model.nq == env.model.nq and model.nu == env.model.nu


def _capsule_surface(model, geom: int, samples: int = 2000) -> np.ndarray:
    """(2·samples, 3) points on a capsule's two end spheres (its extremes lie on them), in its
    body's frame."""
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, model.geom_quat[geom])
    ends = model.geom_pos[geom] + np.outer([1.0, -1.0], model.geom_size[geom][1] * rot.reshape(3, 3)[:, 2])
    directions = np.random.default_rng(geom).normal(size=(samples, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return (ends[:, None, :] + model.geom_size[geom][0] * directions[None]).reshape(-1, 3)


TWO_CUBES = """<mujoco>
  <asset>
    <mesh name="left" vertex="-0.07 -0.01 0  -0.05 -0.01 0  -0.07 0.01 0  -0.05 0.01 0
                               -0.07 -0.01 0.02  -0.05 -0.01 0.02  -0.07 0.01 0.02  -0.05 0.01 0.02"/>
    <mesh name="right" vertex="0.05 -0.01 0  0.07 -0.01 0  0.05 0.01 0  0.07 0.01 0
                                0.05 -0.01 0.02  0.07 -0.01 0.02  0.05 0.01 0.02  0.07 0.01 0.02"/>
  </asset>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 0.1"/>
    <geom name="pad" type="box" size="0.005 0.005 0.005" pos="PAD" contype="1" conaffinity="0"/>
    <body name="object_9" pos="0 0 0">
      <freejoint/>
      <geom name="part_0" type="mesh" mesh="left"/>
      <geom name="part_1" type="mesh" mesh="right"/>
    </body>
  </worldbody>
</mujoco>"""


def _touching(pad_at: str, grip: bool) -> set[tuple[str, str]]:
    """Pairs of geom names in contact for the two-cube object with its hull, the pad at ``pad_at``."""
    spec = mujoco.MjSpec.from_string(TWO_CUBES.replace("PAD", pad_at))
    model = spec.compile()
    hull_collision_spec(spec, model, ["object_9"])
    if grip:
        grip_parts_spec(spec, model, "object_9", ["pad"])
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return {tuple(sorted((model.geom(c.geom1).name, model.geom(c.geom2).name))) for c in data.contact}


def test_the_grasped_object_meets_the_pads_through_its_parts_and_the_rest_through_its_hull():
    between = "0 0 0.01"  # inside the hull, in the gap between the two cubes
    assert ("object_9_hull", "pad") in _touching(between, grip=False)
    assert not any("pad" in pair for pair in _touching(between, grip=True)), "the gap is free"
    inside = "-0.06 0 0.01"
    assert ("pad", "part_0") in _touching(inside, grip=True)
    assert ("floor", "object_9_hull") in _touching(inside, grip=True), "it still rests on its hull"
    assert not any("part" in a or "part" in b for a, b in _touching(inside, grip=True) if "pad" not in (a, b))


def test_sizes_and_control_period_as_mujoco_playground_gives_them(env):
    menv = MjxPickPlace(env, 1, (-0.2, 0.06), cameras=(0, "wrist"), width=32, background=BACKGROUND)
    robot = env.robot
    assert menv.action_size == env.model.nu == len(robot.arm_actuators) + len(robot.gripper_actuators)
    # one step holds the action for ``substeps`` physics steps: the control period (60 Hz over 240 Hz)
    assert menv.dt == pytest.approx(menv.substeps * env.timestep)
    assert menv.dt == pytest.approx(1.0 / script.CONTROL_HZ, rel=0.5 * env.timestep * script.CONTROL_HZ)
    objects = sum(o.id is not None for o in env.objects)
    joints = len(robot.arm_qpos) + len(robot.gripper_qpos)
    assert menv.observation_size == {"joint_pos": (joints,), "joint_vel": (joints,), "object_poses": (objects, 7),
                                     "goal": (2,), "rgb": (2, 24, 32, 3)}
    assert "rgb" not in MjxPickPlace(env, 1, (-0.2, 0.06)).observation_size, "no cameras, no images"


@pytest.mark.slow
def test_eight_worlds_match_mujoco_c_on_the_same_model(env):
    menv = MjxPickPlace(env, 1, (-0.2, 0.06), cameras=(0, "wrist"), width=32, background=BACKGROUND)
    states = jax.jit(jax.vmap(menv.reset))(jax.random.split(jax.random.PRNGKey(0), WORLDS))
    qpos0 = np.asarray(states.data.qpos, np.float64)
    assert np.abs(qpos0[0] - qpos0[1]).max() > 1e-3, "resets differ per world"
    robot = env.robot
    rng = np.random.default_rng(0)
    actions = np.repeat(np.asarray(env.data.ctrl)[None, None], WORLDS, 0).repeat(TICKS, 1)
    actions[..., robot.arm_actuators] += rng.uniform(-0.3, 0.3, (WORLDS, 1, len(robot.arm_actuators)))
    actions[..., robot.gripper_actuators] = rng.uniform(0.0, 0.04, (WORLDS, 1, 1))
    first = jnp.asarray(actions[:, 0], jnp.float32)
    traced = jax.eval_shape(jax.vmap(menv.step), states, first)  # vmap-able (run on accelerators)
    assert traced.data.qpos.shape == states.data.qpos.shape
    step = jax.jit(over_worlds(menv.step))  # on the CPU: lax.map (mjx_env: jaxlib's LAPACK deadlock)
    for t in range(TICKS):
        states = step(states, jnp.asarray(actions[:, t], jnp.float32))
    assert not bool(np.any(states.info["render_overflow"]))
    assert np.abs(np.asarray(states.data.qpos) - qpos0).max() > 0.05, "the arms moved"
    reference = mujoco.MjData(menv.mj_model)
    for w in range(WORLDS):
        mujoco.mj_resetData(menv.mj_model, reference)
        reference.qpos[:] = qpos0[w]
        mujoco.mj_forward(menv.mj_model, reference)
        for t in range(TICKS):
            reference.ctrl[:] = actions[w, t]
            mujoco.mj_step(menv.mj_model, reference, nstep=menv.substeps)
        np.testing.assert_allclose(np.asarray(states.obs["joint_pos"][w]), reference.qpos[menv.joints],
                                   atol=STATE_TOL)
        poses = np.asarray(states.obs["object_poses"][w], np.float64)
        np.testing.assert_allclose(poses[:, :3], reference.xpos[menv.object_bodies], atol=STATE_TOL)
        alignment = np.abs(np.sum(poses[:, 3:] * reference.xquat[menv.object_bodies], axis=1))
        assert np.all(2 * np.arccos(np.clip(alignment, 0.0, 1.0)) <= TURN_TOL)
        env.reset()
        env.data.qpos[:] = reference.qpos
        mujoco.mj_forward(env.model, env.data)
        images = np.asarray(states.obs["rgb"][w])
        assert images.shape == (2, 24, 32, 3)
        for k, camera in enumerate((0, "wrist")):
            cam = env.camera(camera)
            single = np.asarray(env.render(cam.scaled(32 / cam.width), background=BACKGROUND).rgb)
            assert np.abs(images[k] - single).mean() < IMAGE_TOL
    env.reset()
