"""Whether a planned pick-and-place keeps the robot, and the object it carries, clear of the
other objects.

The plan is a joint path; its goal is chosen by the objects' centres. A Panda hand spans 20 cm
across its fingers and stands 10 cm above the fingertips, so a goal 14 cm from a tall box can
put the hand onto the box's top while the object is lowered (the demo scene's can did exactly
that: the hand pushed off the box and the can landed 6.7 cm from its goal). ``first_hit``
replays the path kinematically every ``CHECK_EVERY`` ticks with the fingers open (the widest
the hand gets) and the carried object moving rigidly with the hand from the lift to the
release, and reports the first pair that comes within ``CLEARANCE``: a robot geom or the
carried object's against another object's geoms (MuJoCo's signed distances of the collision
geometry, after a bounding-sphere cull). Supports are not checked: the fingers reach down
towards them by design, and the object is set down on them.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from phirie_jax.rotations import matrix_to_quat

CLEARANCE = 0.003     # m: closer than this to another object counts as a hit
CHECK_EVERY = 6       # ticks between checks (0.1 s at 60 Hz: the hand moves < 3 cm)


@dataclasses.dataclass(frozen=True)
class Hit:
    """The first contact along a path: what moved into which object, when."""

    tick: int
    segment: str
    mover: str            # "the robot's <body>" or "the carried object"
    other: int            # the object id it would hit
    distance: float       # m, signed (negative: inside)


def _colliding(model, bodies) -> np.ndarray:
    bodies = np.asarray(sorted(bodies))
    mask = np.isin(model.geom_bodyid, bodies) & ((model.geom_contype | model.geom_conaffinity) > 0)
    return np.flatnonzero(mask)


def _segment(marks, tick: int) -> str:
    name = marks[0][0]
    for segment, start in marks:
        if start <= tick:
            name = segment
    return name


def first_hit(env, object_id: int, rows: np.ndarray, marks, every: int = CHECK_EVERY) -> Hit | None:
    """The first ``Hit`` along the arm path ``rows`` (T, n) with segments ``marks`` ((name, first
    tick), ...: the carried stretch runs from 'lift' to 'release'), or None when it stays clear."""
    import mujoco

    model, robot = env.model, env.robot
    data = mujoco.MjData(model)
    data.qpos[:] = env.data.qpos
    robot.set_home(model, data)  # the fingers open; the arm is set per tick below
    target = env.object(object_id).body_id
    free = int(model.jnt_qposadr[model.body_jntadr[target]])
    starts = dict(marks)
    lift, release = starts.get("lift", len(rows)), starts.get("release", len(rows))
    movers = _colliding(model, set(robot.bodies[1:]))  # the mount's stand stays where it is
    carried = _colliding(model, {target})
    others = _colliding(model, {o.body_id for o in env.objects if o.id not in (None, object_id)})
    if not len(others):
        return None
    owner = {o.body_id: o.id for o in env.objects if o.id is not None}
    ticks = sorted(set(range(0, len(rows), every)) | {min(lift, len(rows) - 1), min(release, len(rows) - 1),
                                                      len(rows) - 1})
    grasp = rows[max(lift - 1, 0)]  # the last tick of 'close': the hand at the grasp
    relative = np.linalg.inv(_site_pose(model, data, robot, grasp)) @ _body_pose(data, target)
    for tick in ticks:
        carrying = lift <= tick
        if carrying:  # the object rides with the hand from the lift; it stays where it was released
            held = _site_pose(model, data, robot, rows[min(tick, release)]) @ relative
            data.qpos[free:free + 3], data.qpos[free + 3:free + 7] = held[:3, 3], matrix_to_quat(held[:3, :3])
        data.qpos[robot.arm_qpos] = rows[tick]
        mujoco.mj_kinematics(model, data)
        moving = np.concatenate([movers, carried]) if carrying else movers
        hit = _closest(model, data, moving, others)
        if hit is not None:
            geom, other, distance = hit
            body = int(model.geom_bodyid[geom])
            mover = "the carried object" if body == target else f"the robot's {model.body(body).name.split('/')[-1]}"
            return Hit(tick, _segment(marks, tick), mover, owner[int(model.geom_bodyid[other])], distance)
    return None


def _closest(model, data, moving: np.ndarray, others: np.ndarray) -> tuple[int, int, float] | None:
    """(moving geom, other geom, distance) of the closest pair within ``CLEARANCE``, or None."""
    import mujoco

    gap = (np.linalg.norm(data.geom_xpos[moving][:, None] - data.geom_xpos[others][None], axis=-1)
           - model.geom_rbound[moving][:, None] - model.geom_rbound[others][None])
    best = None
    for i, j in zip(*np.nonzero(gap < CLEARANCE)):
        distance = mujoco.mj_geomDistance(model, data, int(moving[i]), int(others[j]), CLEARANCE, None)
        if distance < CLEARANCE and (best is None or distance < best[2]):
            best = (int(moving[i]), int(others[j]), float(distance))
    return best


def _site_pose(model, data, robot, q: np.ndarray) -> np.ndarray:
    """(4, 4) the end-effector site's pose with the arm at ``q`` (``data`` is left posed there)."""
    import mujoco

    data.qpos[robot.arm_qpos] = q
    mujoco.mj_kinematics(model, data)
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = data.site_xmat[robot.site].reshape(3, 3), data.site_xpos[robot.site]
    return out


def _body_pose(data, body: int) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = data.xmat[body].reshape(3, 3), data.xpos[body]
    return out
