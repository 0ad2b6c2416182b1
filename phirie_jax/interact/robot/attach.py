"""The merge: a robot's spec attached to the scene's world with ``MjSpec`` attach (no XML text edits).

``attach_robot(scene, robot, description, base, floor_height)`` edits the scene spec in place:

* a static mount body ``robot_mount`` at the base pose, holding a box stand from the floor up to
  the base when the base is above the floor (a robot beside a table stands on something);
* the robot's root body attached under it, every name prefixed ``robot/`` (``PREFIX``);
* gravity compensation on every robot body (``gravcomp = 1``): the position servos then hold a
  pose without sagging, as a real arm's torque controller does;
* contact margins of the robot's geoms set to 0 (MJX has no margin for mesh contacts, and the
  single and batched environments run the same model);
* the implicit-in-velocity integrator (``implicitfast``): the servos' and joints' damping are
  integrated implicitly, so the arm is stable at the scene's 240 Hz step;
* a wrist camera ``robot/wrist`` on the hand, looking at the point between the fingertips.

The robot's own simulator options are aligned to the scene's before attaching (the scene's
timestep and solver settings win), so MuJoCo reports no attach conflicts.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from phirie_jax.interact.robot.model import RobotDescription
from phirie_jax.rotations import matrix_to_quat, quat_to_matrix

PREFIX = "robot/"
MOUNT = "robot_mount"
STAND = "robot_stand"
WRIST_CAMERA = "wrist"
STAND_MARGIN = 0.01        # the stand's top overhangs the root body's footprint by this, m
STAND_MIN_HEIGHT = 0.01    # a base closer than this to the floor stands on the floor itself, m
STAND_RGBA = (0.22, 0.22, 0.24, 1.0)
WRIST_BACK = 0.1           # a generic robot's wrist camera: this far behind its end-effector site, m
OPTION_FIELDS = ("timestep", "gravity", "integrator", "cone", "jacobian", "solver", "iterations", "ls_iterations",
                 "tolerance", "ls_tolerance", "noslip_iterations", "impratio", "density", "viscosity",
                 "wind", "magnetic", "disableflags", "enableflags")
USER_SIZES = ("nuser_body", "nuser_jnt", "nuser_geom", "nuser_site", "nuser_cam", "nuser_tendon",
              "nuser_actuator", "nuser_sensor")


@dataclasses.dataclass(frozen=True)
class Base:
    """Where the robot's root body stands: position (3,) in the scene and yaw about +z (rad)."""

    position: np.ndarray
    yaw: float

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) base → scene."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        out = np.eye(4)
        out[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
        out[:3, 3] = self.position
        return out

    @property
    def quat(self) -> list[float]:
        return [float(np.cos(self.yaw / 2)), 0.0, 0.0, float(np.sin(self.yaw / 2))]

    def record(self) -> dict:
        return {"position": [float(v) for v in self.position], "yaw_deg": float(np.degrees(self.yaw))}


def footprint(robot_model, description: RobotDescription) -> tuple[np.ndarray, np.ndarray]:
    """(2,) low and (2,) high corner of the root body's collision geometry in its own xy frame."""
    from phirie_jax.interact.mjx_model import body_frame_vertices

    verts = body_frame_vertices(robot_model, robot_model.body(description.root_body).id)
    if not len(verts):
        return np.full(2, -0.05), np.full(2, 0.05)
    return verts[:, :2].min(0), verts[:, :2].max(0)


def look_at_quat(position, target, up_hint) -> np.ndarray:
    """(4,) wxyz orientation of a MuJoCo camera at ``position`` looking at ``target`` (it looks
    along its −z with +y up; ``up_hint`` picks the roll)."""
    back = np.asarray(position, float) - np.asarray(target, float)
    z = back / np.linalg.norm(back)
    x = np.cross(up_hint, z)
    x /= np.linalg.norm(x)
    return matrix_to_quat(np.stack([x, np.cross(z, x), z], axis=1))


def _align_globals(scene, robot) -> None:
    for name in OPTION_FIELDS:
        setattr(robot.option, name, getattr(scene.option, name))
    for name in USER_SIZES:
        wanted = max(getattr(scene, name), getattr(robot, name))
        setattr(scene, name, wanted)
        setattr(robot, name, wanted)


def _wrist_pose(robot_model, description: RobotDescription) -> tuple[str, np.ndarray, np.ndarray]:
    """(body, position, wxyz quat) of the wrist camera in the body's frame."""
    if description.wrist is not None:
        body, position, target = description.wrist
        return body, np.asarray(position, float), look_at_quat(position, target, up_hint=np.asarray(position) * [1, 1, 0])
    site = robot_model.site(description.end_effector)
    body = robot_model.body(int(robot_model.site_bodyid[site.id])).name
    rot = quat_to_matrix(robot_model.site_quat[site.id])
    approach = rot[:, 2]
    target = robot_model.site_pos[site.id]
    position = target - WRIST_BACK * approach
    return body, position, look_at_quat(position, target, up_hint=rot[:, 0])


def attach_robot(scene, robot, description: RobotDescription, base: Base, floor_height: float,
                 wrist_camera: bool = True, wrist_fovy: float = 75.0) -> None:
    """Merge ``robot`` (a spec, ``model.robot_spec``) into ``scene`` at ``base`` (module docstring)."""
    import mujoco

    robot_model = robot.compile()
    low, high = footprint(robot_model, description)
    for key in list(robot.keys):
        robot.delete(key)  # keyframes of the robot alone do not size the scene's qpos
    for geom in robot.geoms:
        geom.margin, geom.gap = 0.0, 0.0
    _align_globals(scene, robot)

    mount = scene.worldbody.add_body(name=MOUNT, pos=base.position.tolist(), quat=base.quat)
    height = float(base.position[2] - floor_height)
    if height > STAND_MIN_HEIGHT:
        half = 0.5 * (high - low) + STAND_MARGIN
        centre = 0.5 * (high + low)
        mount.add_geom(name=STAND, type=mujoco.mjtGeom.mjGEOM_BOX, size=[half[0], half[1], 0.5 * height],
                       pos=[centre[0], centre[1], -0.5 * height], rgba=list(STAND_RGBA))
    frame = mount.add_frame()
    root = frame.attach_body(robot.body(description.root_body), PREFIX, "")
    root.gravcomp = 1.0
    for body in root.find_all(mujoco.mjtObj.mjOBJ_BODY):
        body.gravcomp = 1.0
    if wrist_camera:
        body, position, quat = _wrist_pose(robot_model, description)
        scene.body(PREFIX + body).add_camera(name=PREFIX + WRIST_CAMERA, pos=position.tolist(), quat=quat.tolist(),
                                             fovy=float(wrist_fovy))
    scene.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
