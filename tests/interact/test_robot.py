"""A robot in the converted scene: the merge, its Gaussians, its cameras, its kinematics, the
scripted pick-and-place and the one-line errors of bad input."""

from __future__ import annotations

import importlib.util

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kernels.gaussians import Sim3, transform_gaussians
from phirie_jax.errors import SceneInputError
from phirie_jax.interact.environment import Environment
from phirie_jax.interact.robot import script
from phirie_jax.interact.robot.attach import PREFIX, STAND
from phirie_jax.interact.robot.config import RobotConfig
from phirie_jax.interact.robot.kinematics import Kinematics, dls_step
from phirie_jax.interact.robot.model import robot_spec
from phirie_jax.render import render

IMAGE_TOL = 2e-4          # float32 rasterization of identically placed Gaussians
FD_TOL = 1e-5             # Jacobian against central differences (step 1e-6)
IK_TOL = 2e-3             # m: the solver's position tolerance
DLS_TOL = 1e-10
KNOCKED = 0.005           # m: the box moved by a hand or a can that hit it
VISIBLE = 0.1             # a pixel's largest channel change that one sees
SEEN_ELSEWHERE = 0.01     # fraction of the wrist image that visibly changes when the hand swings
COARSE = RobotConfig(spacing=0.02)    # few robot Gaussians: fast renders
WIDTH = 64                # px of every test render (one compiled renderer for them all)


@pytest.fixture(scope="module")
def env(converted):
    return Environment.load(converted[0], robot=COARSE)


def test_merge_keeps_the_scenes_objects_and_supports(converted, env):
    plain = Environment.load(converted[0])
    for o in plain.objects:
        merged = env.object(o.id)
        np.testing.assert_allclose(env.model.body(o.body).pos, plain.model.body(o.body).pos)
        assert env.model.body_mass[merged.body_id] == pytest.approx(plain.model.body_mass[o.body_id])
    for g in range(plain.model.ngeom):
        name = plain.model.geom(g).name
        np.testing.assert_allclose(env.model.geom(name).size, plain.model.geom(g).size)
        np.testing.assert_allclose(env.model.geom(name).pos, plain.model.geom(g).pos)
    assert env.model.nu == 9 and env.model.njnt == plain.model.njnt + 9
    assert all(env.model.body(b).name.startswith(PREFIX) for b in env.robot.bodies[1:])
    placement = env.robot.placement
    assert placement.source == "default" and placement.support == "support_0"
    assert sorted(placement.reachable) == [1, 2, 3]
    # the stand reaches from the floor up to the base, at the tabletop's height
    stand = env.model.geom(STAND)
    top = env.data.geom_xpos[stand.id][2] + stand.size[2]
    assert top == pytest.approx(0.75, abs=1e-6) and env.data.geom_xpos[stand.id][2] - stand.size[2] == pytest.approx(0)
    # the arm holds its home pose (gravity compensated servos): 1 s later it has not moved
    env.reset()
    before = env.robot.end_effector(env.data)[0]
    env.step(240)
    assert np.linalg.norm(env.robot.end_effector(env.data)[0] - before) < 1e-3
    env.reset()


def small(camera):
    return camera.scaled(WIDTH / camera.width)


def test_a_joint_turned_by_a_known_angle_renders_like_the_gaussians_turned_directly(env):
    env.reset()
    joint = env.model.joint(PREFIX + env.robot.description.arm_joints[3])
    angle = 0.4
    home = env.gaussians()
    anchor, axis = env.data.xanchor[joint.id].copy(), env.data.xaxis[joint.id].copy()
    distal = {b for b in env.robot.bodies if _below(env.model, int(joint.bodyid[0]), b)}
    env.data.qpos[joint.qposadr[0]] += angle
    mujoco.mj_forward(env.model, env.data)
    view = small(env.camera(1))
    got = render(env.gaussians(), view)

    # the links beyond the joint, turned directly about its axis through its anchor
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec(angle * axis).as_matrix()
    turn[:3, 3] = anchor - turn[:3, :3] @ anchor
    start = env.background.means.shape[0]
    rows = jnp.asarray(np.concatenate([np.arange(o.gaussians.start, o.gaussians.stop) + start
                                       for o in env.objects if o.id is None and o.body_id in distal]))
    turned = transform_gaussians(jax.tree.map(lambda x: x[rows], home),
                                 Sim3.from_matrix(jnp.asarray(turn, jnp.float32)))
    direct = render(jax.tree.map(lambda full, part: full.at[rows].set(part), home, turned), view)
    assert len(distal) >= 5
    for field in ("rgb", "alpha", "depth"):
        np.testing.assert_allclose(getattr(got, field), getattr(direct, field), atol=IMAGE_TOL)
    untouched = render(home, view)
    assert float(jnp.max(jnp.abs(untouched.rgb - got.rgb))) > 0.1, "the arm moved in view"
    env.reset()


def _below(model, ancestor: int, body: int) -> bool:
    while body > 0:
        if body == ancestor:
            return True
        body = int(model.body_parentid[body])
    return False


def test_the_wrist_camera_moves_with_the_hand(env):
    env.reset()
    hand = env.model.camera(env.robot.camera).bodyid[0]

    def in_hand_frame(cam):
        body = np.eye(4)
        body[:3, :3], body[:3, 3] = env.data.xmat[hand].reshape(3, 3), env.data.xpos[hand]
        return cam.world_to_camera @ body

    first = env.camera("wrist")
    relative = in_hand_frame(first)
    image = render(env.gaussians(), small(first))
    env.data.qpos[env.robot.arm_qpos[0]] += 0.5
    mujoco.mj_forward(env.model, env.data)
    moved = env.camera("wrist")
    np.testing.assert_allclose(in_hand_frame(moved), relative, atol=1e-9)
    assert np.linalg.norm(moved.center - first.center) > 0.05
    change = jnp.abs(render(env.gaussians(), small(moved)).rgb - image.rgb).max(axis=-1)
    assert float(jnp.mean(change > VISIBLE)) > SEEN_ELSEWHERE, "the view moved over the scene"
    env.reset()
    assert "wrist" in env.camera_names()


def test_dls_step_is_the_regularized_least_squares_solution():
    rng = np.random.default_rng(0)
    for m, n in ((6, 7), (3, 7), (6, 4)):
        jac, err, damping = rng.normal(size=(m, n)), rng.normal(size=m), 0.1
        stacked = np.vstack([jac, damping * np.eye(n)])
        reference = np.linalg.lstsq(stacked, np.concatenate([err, np.zeros(n)]), rcond=None)[0]
        np.testing.assert_allclose(dls_step(jac, err, damping), reference, atol=DLS_TOL)


@pytest.fixture(scope="module")
def panda():
    spec, description = robot_spec("panda")
    return Kinematics(spec.compile(), description.end_effector, description.arm_joints), description


def test_the_jacobian_matches_central_differences_of_forward_kinematics(panda):
    kin, description = panda
    q = np.asarray(description.home) + 0.1
    jac = kin.jacobian(q)
    h = 1e-6
    for i in range(len(q)):
        dq = np.zeros_like(q)
        dq[i] = h
        (p1, r1), (p0, r0) = kin.forward(q + dq), kin.forward(q - dq)
        np.testing.assert_allclose(jac[:3, i], (p1 - p0) / (2 * h), atol=FD_TOL)
        omega = Rotation.from_matrix(r1 @ r0.T).as_rotvec() / (2 * h)
        np.testing.assert_allclose(jac[3:, i], omega, atol=FD_TOL)


def test_ik_reaches_poses_the_arm_can_take(panda):
    kin, description = panda
    rng = np.random.default_rng(1)
    home = np.asarray(description.home)
    for _ in range(5):
        q = np.clip(home + rng.uniform(-0.5, 0.5, len(home)), kin.low, kin.high)
        position, rotation = kin.forward(q)
        result = kin.solve(position, rotation, q0=home)
        assert result.converged, result
        got, got_rot = kin.forward(result.q)
        assert np.linalg.norm(got - position) <= IK_TOL
        assert np.linalg.norm(Rotation.from_matrix(got_rot @ rotation.T).as_rotvec()) <= 0.02
    far = kin.solve([3.0, 0.0, 0.3], q0=home, iterations=50)
    assert not far.converged and far.position_error > 1.0


def test_pick_and_place_moves_the_box_to_its_goal_upright(env):
    env.reset()
    box = 1
    grasp = script.grasp_for(env, box)
    assert grasp.fits
    goal = grasp.centre[:2] + np.array([0.0, -0.12])
    start_rotation = env.data.xmat[env.object(box).body_id].reshape(3, 3).copy()
    plan = script.plan_pick_place(env, box, goal)
    heights = []
    script.run_plan(env, plan, on_tick=lambda k: heights.append(env.data.xpos[env.object(box).body_id][2]))
    result = script.outcome(env, box, goal, start_rotation)
    assert result["success"], result
    assert max(heights) - heights[0] > 0.1, "carried, not pushed"
    assert np.linalg.norm(env.robot.arm_q(env.data) - env.robot.home) < 0.05, "returned home"
    env.reset()


def test_a_plan_into_another_object_is_refused_and_would_have_moved_it(env, monkeypatch):
    env.reset()
    box, can = script.grasp_for(env, 1), script.grasp_for(env, 3)
    goal = box.centre[:2] - 0.13 * can.normal[:2]  # the can set down beside the tall box, fingers towards it
    with pytest.raises(script.UnreachableError, match="would hit object 1") as err:
        script.plan_pick_place(env, 3, goal)
    assert "\n" not in str(err.value)
    monkeypatch.setattr(script, "first_hit", lambda *args, **kwargs: None)  # run it anyway
    env.reset()
    before = env.data.xpos[env.object(1).body_id].copy()
    script.run_plan(env, script.plan_pick_place(env, 3, goal))
    assert np.linalg.norm(env.data.xpos[env.object(1).body_id] - before) > KNOCKED, "a real collision"
    env.reset()


def test_bad_input_is_one_line(converted, env, tmp_path):
    broken = tmp_path / "arm.xml"
    broken.write_text("<mujoco><worldbody><body name='a'><geom type='box'/></body></worldbody></mujoco>")
    with pytest.raises(SceneInputError, match="MuJoCo cannot compile it") as err:
        Environment.load(converted[0], robot=str(broken))
    assert "\n" not in str(err.value) and str(broken) in str(err.value)
    with pytest.raises(SceneInputError, match="into support_0") as err:
        Environment.load(converted[0], robot=RobotConfig(base=(0.45, 0.25, 0.7, 0.0), spacing=0.05))
    assert "\n" not in str(err.value)
    env.reset()
    with pytest.raises(script.UnreachableError, match="out of the arm's reach|not on the support") as err:
        script.plan_pick_place(env, 1, (2.5, 0.0))
    with pytest.raises(script.UnreachableError, match="does not fit the gripper"):
        script.plan_pick_place(env, 2, (0.0, 0.0))      # the fruit: wider than the open gripper
    with pytest.raises(script.UnreachableError, match="out of the arm's reach"):
        script.plan_pick_place(env, 1, (0.55, -0.35))   # on the table, beyond the arm
    assert "\n" not in str(err.value)


def test_a_missing_robot_package_names_what_to_install(converted, monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "gymnasium_robotics" else real(name, *a))
    with pytest.raises(SceneInputError, match=r"pip install 'phirie_jax\[robot\]'"):
        Environment.load(converted[0], robot="panda")
