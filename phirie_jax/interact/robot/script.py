"""Scripted pick-and-place: reach, grasp, lift, carry, place, release, return.

``plan_pick_place(env, object_id, goal)`` turns the task into a ``Plan``: the controls of every
control tick (arm servo targets from inverse kinematics along the end-effector path, gripper
open or closed). The plan is a function of the initial state only, so the same plan runs in the
single MuJoCo environment (``run_plan``) and in batched MJX worlds (``interact.mjx_env``).

Servo lag: a position servo with stiffness kp and joint damping b settles at q = u − (b/kp) q̇
while the joint moves, so each arm target is led by (b/kp) times the planned joint velocity
(``lead``): the arm follows the planned path instead of trailing it by centimetres.

The grasp is top-down: the fingers close across the object's narrowest horizontal width
(rotating calipers on its collision hull), at a depth that keeps the fingertips above the
support; an object wider than the open gripper (less ``FIT_MARGIN``) does not fit. The end
effector moves along straight segments with smooth (quintic) timing; the rotation turns to the
grasp's during the approach and is kept until the arm returns home in joint space.

A plan whose path would bring the robot, or the object it carries, into another object is
refused (``clearance.first_hit``), as a goal out of reach is: ``UnreachableError``.

Success (``outcome``): the object's centre within ``SUCCESS_DISTANCE`` of the goal and its up
axis within ``UPRIGHT_DEG`` of where it was.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from phirie_jax.interact.robot.clearance import first_hit
from phirie_jax.interact.robot.placement import object_centres, scene_supports
from phirie_jax.rotations import matrix_to_rotvec, slerp_matrix

SUCCESS_DISTANCE = 0.03   # m (the 3 cm)
UPRIGHT_DEG = 10.0
FIT_MARGIN = 0.005        # m of the opening kept free around the object
GRASP_BELOW_TOP = 0.02    # m: the site this far below the object's top ...
TIP_CLEARANCE = 0.01      # m: ... unless the fingertips would come closer than this to the support
PLACE_DROP = 0.005        # m: the object is released this far above the support
CONTROL_HZ = 60.0
WAYPOINT_TOL = 0.01       # m: a waypoint IK farther off than this is unreachable


@dataclasses.dataclass(frozen=True)
class PickPlaceConfig:
    """Heights (m) and durations (s) of the script's segments."""

    approach: float = 0.12
    lift: float = 0.15
    reach_s: float = 1.5
    hover_s: float = 0.3
    descend_s: float = 1.0
    close_s: float = 0.8
    lift_s: float = 1.0
    carry_s: float = 1.6
    lower_s: float = 1.0
    release_s: float = 0.6
    retreat_s: float = 0.8
    home_s: float = 1.4
    settle_s: float = 0.5


class UnreachableError(ValueError):
    """A task the robot cannot do (out of reach, too wide for the gripper): one line for people."""


@dataclasses.dataclass(frozen=True)
class Grasp:
    centre: np.ndarray      # (3,) x, y of the object's centre; z its top
    bottom: float           # m, the object's lowest point
    width: float            # m, narrowest horizontal width
    normal: np.ndarray      # (3,) horizontal unit axis the fingers close along
    fits: bool


@dataclasses.dataclass(frozen=True)
class Plan:
    """Controls of every tick (T, nu) at ``hz``, and each segment's name and first tick."""

    ctrl: np.ndarray
    hz: float
    segments: tuple[tuple[str, int], ...]
    object_id: int
    goal: np.ndarray        # (2,)

    @property
    def seconds(self) -> float:
        return len(self.ctrl) / self.hz


def _hull_width(xy: np.ndarray) -> tuple[float, np.ndarray]:
    """Narrowest width of a 2D point set (N, 2) and the unit direction (2,) it is measured along."""
    from scipy.spatial import ConvexHull

    hull = xy[ConvexHull(xy).vertices]
    best = (np.inf, np.array([1.0, 0.0]))
    for a, b in zip(hull, np.roll(hull, -1, axis=0)):
        edge = (b - a) / max(np.linalg.norm(b - a), 1e-12)
        normal = np.array([-edge[1], edge[0]])
        width = float(np.ptp(hull @ normal))
        if width < best[0]:
            best = (width, normal)
    return best


def grasp_for(env, object_id: int) -> Grasp:
    """Where and across which width the gripper takes an object, in its current pose."""
    from phirie_jax.interact.mjx_model import body_frame_vertices

    body = env.object(object_id).body_id
    verts = body_frame_vertices(env.model, body) @ env.data.xmat[body].reshape(3, 3).T + env.data.xpos[body]
    width, normal = _hull_width(verts[:, :2])
    centre = object_centres(env.model, env.data, [body])[0]
    opening = gripper_opening(env)
    return Grasp(centre, float(verts[:, 2].min()), width, np.array([*normal, 0.0]), width <= opening - FIT_MARGIN)


def gripper_opening(env) -> float:
    """Distance between the open fingers: the gripper joints' travel (slide joints, m)."""
    robot, model = env.robot, env.model
    joints = [int(np.flatnonzero(model.jnt_qposadr == a)[0]) for a in robot.gripper_qpos]
    return float(sum(model.jnt_range[j, 1] - model.jnt_range[j, 0] for j in joints))


def fingertip_below_site(env) -> float:
    """How far (m) the gripper's lowest collision point lies below the end-effector site along its
    approach axis (the site's z), in the current state."""
    import mujoco

    from phirie_jax.interact.mjx_model import body_frame_vertices

    robot, model, data = env.robot, env.model, env.data
    pos, rot = robot.end_effector(data)
    bodies = {int(model.jnt_bodyid[np.flatnonzero(model.jnt_qposadr == a)[0]]) for a in robot.gripper_qpos}
    depth = 0.0
    for b in bodies:  # mesh vertices, and each primitive's centre plus its radius
        world = body_frame_vertices(model, b) @ data.xmat[b].reshape(3, 3).T + data.xpos[b]
        if len(world):
            depth = max(depth, float(np.max((world - pos) @ rot[:, 2])))
        for g in np.flatnonzero(model.geom_bodyid == b):
            if model.geom_type[g] != mujoco.mjtGeom.mjGEOM_MESH:
                depth = max(depth, float((data.geom_xpos[g] - pos) @ rot[:, 2] + model.geom_size[g][0]))
    return depth


def grasp_rotation(env, normal: np.ndarray) -> np.ndarray:
    """(3, 3) site rotation pointing down with the gripper's opening axis along ±``normal``,
    the sign that turns the hand least from its current rotation."""
    robot = env.robot
    axis = robot.opening_axis(env.model, env.data)
    down = np.array([0.0, 0.0, -1.0])
    site_frame = np.stack([axis, np.cross([0.0, 0.0, 1.0], axis), [0.0, 0.0, 1.0]], axis=1)
    _, current = robot.end_effector(env.data)
    best = None
    for sign in (1.0, -1.0):
        n = sign * normal
        world_frame = np.stack([n, np.cross(down, n), down], axis=1)
        rot = world_frame @ site_frame.T
        angle = np.linalg.norm(matrix_to_rotvec(rot @ current.T))
        if best is None or angle < best[0]:
            best = (angle, rot)
    return best[1]


def _smooth(s: np.ndarray) -> np.ndarray:
    """Quintic time scaling: 0 → 1 with zero velocity and acceleration at both ends."""
    return s**3 * (10 - 15 * s + 6 * s**2)


def plan_pick_place(env, object_id: int, goal, config: PickPlaceConfig = PickPlaceConfig()) -> Plan:
    """The controls that move ``object_id`` to ``goal`` (x, y) and bring the arm home."""
    robot = env.robot
    if robot is None:
        raise ValueError("this environment has no robot: load it with robot='panda'")
    goal = np.asarray(goal, np.float64)[:2]
    grasp = grasp_for(env, object_id)
    if not grasp.fits:
        raise UnreachableError(f"object {object_id} does not fit the gripper: its narrowest width "
                               f"{100 * grasp.width:.1f} cm needs an opening of {100 * (grasp.width + FIT_MARGIN):.1f} cm "
                               f"(the gripper opens {100 * gripper_opening(env):.1f} cm)")
    _check_on_support(env, object_id, goal, grasp)
    tip = fingertip_below_site(env)
    site_z = max(grasp.centre[2] - GRASP_BELOW_TOP, grasp.bottom + tip + TIP_CLEARANCE)
    place_z = site_z + PLACE_DROP
    rot = grasp_rotation(env, grasp.normal)
    start_pos, start_rot = robot.end_effector(env.data)
    at_object, at_goal = np.array([*grasp.centre[:2], site_z]), np.array([*goal, place_z])
    up = lambda p, h: p + [0.0, 0.0, h]  # noqa: E731
    closed, opened = 1.0, 0.0
    segments = [  # name, seconds, end position, gripper
        ("reach", config.reach_s, up(at_object, config.approach), opened),
        ("hover", config.hover_s, up(at_object, config.approach), opened),
        ("descend", config.descend_s, at_object, opened),
        ("close", config.close_s, at_object, closed),
        ("lift", config.lift_s, up(at_object, config.lift), closed),
        ("carry", config.carry_s, up(at_goal, config.lift), closed),
        ("hover", config.hover_s, up(at_goal, config.lift), closed),
        ("lower", config.lower_s, at_goal, closed),
        ("release", config.release_s, at_goal, opened),
        ("retreat", config.retreat_s, up(at_goal, config.approach), opened),
    ]
    kin, q = robot.kinematics, robot.arm_q(env.data)
    rows, grips, marks, pos = [], [], [], start_pos
    for index, (name, seconds, end, gripper) in enumerate(segments):
        marks.append((name, len(rows)))
        ticks = max(1, int(round(seconds * CONTROL_HZ)))
        for s in _smooth(np.arange(1, ticks + 1) / ticks):
            target = pos + s * (end - pos)
            target_rot = slerp_matrix(start_rot, rot, s) if index == 0 else rot
            result = kin.solve(target, target_rot, q0=q, iterations=60)
            if result.position_error > WAYPOINT_TOL:
                where = f"object {object_id}" if index < 5 else f"the goal ({goal[0]:.3f}, {goal[1]:.3f}) of object {object_id}"
                raise UnreachableError(f"{where} is out of the arm's reach from its base: the hand stays "
                                       f"{100 * result.position_error:.1f} cm short of ({target[0]:.3f}, {target[1]:.3f}, "
                                       f"{target[2]:.3f}) during '{name}'")
            q = result.q
            rows.append(q)
            grips.append(gripper)
        pos = end
    marks.append(("home", len(rows)))
    ticks = max(1, int(round(config.home_s * CONTROL_HZ)))
    for s in _smooth(np.arange(1, ticks + 1) / ticks):
        rows.append(q + s * (robot.home - q))
        grips.append(opened)
    marks.append(("settle", len(rows)))
    rows += [rows[-1]] * max(1, int(round(config.settle_s * CONTROL_HZ)))
    grips += [opened] * (len(rows) - len(grips))
    hit = first_hit(env, object_id, np.asarray(rows), marks)
    if hit is not None:
        raise UnreachableError(f"object {object_id} to ({goal[0]:.3f}, {goal[1]:.3f}): {hit.mover} would hit object "
                               f"{hit.other} during '{hit.segment}' (expected a path clear of the other objects)")
    ctrl = np.repeat(env.data.ctrl[None], len(rows), axis=0)
    ctrl[:, robot.arm_actuators] = lead(env.model, robot, np.asarray(rows), CONTROL_HZ)
    ctrl[:, robot.gripper_actuators] = np.stack([robot.gripper(g) for g in grips])
    return Plan(ctrl, CONTROL_HZ, tuple(marks), object_id, goal)


def lead(model, robot, path: np.ndarray, hz: float) -> np.ndarray:
    """(T, n) servo targets that make the arm follow the joint ``path`` (T, n) sampled at ``hz``:
    each target leads by (b/kp) q̇ (module docstring), clipped to the control ranges."""
    velocity = np.gradient(path, 1.0 / hz, axis=0) if len(path) > 1 else np.zeros_like(path)
    kp = model.actuator_gainprm[robot.arm_actuators, 0]
    damping = model.dof_damping[robot.arm_dofs] - model.actuator_biasprm[robot.arm_actuators, 2]
    ranges = model.actuator_ctrlrange[robot.arm_actuators]
    return np.clip(path + (damping / kp) * velocity, ranges[:, 0], ranges[:, 1])


def _check_on_support(env, object_id: int, goal: np.ndarray, grasp: Grasp) -> None:
    """The goal must lie on a support top at the object's height (or on the floor it stands on)."""
    floor, supports = scene_supports(env.model, env.data)
    for s in supports:
        local = s.axes @ (np.array([*goal, s.centre[2]]) - s.centre)
        if abs(s.centre[2] - grasp.bottom) < 0.02 and np.all(np.abs(local) <= s.half):
            return
    if abs(grasp.bottom - floor) < 0.02:
        return
    raise UnreachableError(f"goal ({goal[0]:.3f}, {goal[1]:.3f}) of object {object_id} is not on the support it "
                           "stands on (expected a point on that support's top)")


def run_plan(env, plan: Plan, on_tick=None) -> None:
    """Run ``plan`` in the single environment: each tick's controls held for 1/hz seconds;
    ``on_tick(tick)`` after each (e.g. to render a frame)."""
    steps = substeps(env.timestep, plan.hz)
    for tick, ctrl in enumerate(plan.ctrl):
        env.data.ctrl[:] = ctrl
        env.step(steps)
        if on_tick is not None:
            on_tick(tick)


def substeps(timestep: float, hz: float) -> int:
    """Simulator steps per control tick."""
    return max(1, int(round(1.0 / (hz * timestep))))


def outcome(env, object_id: int, goal, start_rotation: np.ndarray) -> dict:
    """Whether the object stands at the goal: its centre's distance (m), tilt (deg) and success."""
    body = env.object(object_id).body_id
    centre = object_centres(env.model, env.data, [body])[0]
    distance = float(np.linalg.norm(centre[:2] - np.asarray(goal, np.float64)[:2]))
    relative = env.data.xmat[body].reshape(3, 3) @ np.asarray(start_rotation).T
    tilt = float(np.degrees(np.arccos(np.clip(relative[2, 2], -1.0, 1.0))))
    return {"object": object_id, "goal": [float(v) for v in np.asarray(goal)[:2]], "distance_m": distance,
            "tilt_deg": tilt, "success": bool(distance <= SUCCESS_DISTANCE and tilt <= UPRIGHT_DEG)}
