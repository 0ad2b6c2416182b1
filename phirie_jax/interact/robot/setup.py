"""The robot in a scene: ``merge_robot`` builds it into a scene spec; ``Robot`` is the handle the
environment, the scripts and the policy APIs drive it through (ids in the merged model)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from phirie_jax.errors import SceneInputError
from phirie_jax.interact.robot import placement as place
from phirie_jax.interact.robot.attach import MOUNT, PREFIX, WRIST_CAMERA, Base, attach_robot, footprint
from phirie_jax.interact.robot.config import RobotConfig
from phirie_jax.interact.robot.kinematics import Kinematics
from phirie_jax.interact.robot.model import RobotDescription, robot_spec

REACH_ITERATIONS = 100   # IK iterations of a reach check (a reachable top-down pose needs < 40)


@dataclasses.dataclass(frozen=True)
class Robot:
    """The merged robot (names in ``description`` are unprefixed; ids are the merged model's)."""

    config: RobotConfig
    description: RobotDescription
    placement: place.Placement
    bodies: tuple[int, ...]            # every robot body, the mount first
    arm_qpos: np.ndarray               # (n,) qpos addresses of the arm joints
    arm_dofs: np.ndarray               # (n,) dof addresses
    arm_actuators: np.ndarray          # (n,) actuator ids of their servos
    gripper_qpos: np.ndarray           # (g,) qpos addresses of the gripper joints
    gripper_actuators: np.ndarray      # (a,) actuator ids
    gripper_open: np.ndarray           # (a,) control of the open gripper (top of each range)
    gripper_closed: np.ndarray         # (a,) control of the closed gripper (bottom of each range)
    home: np.ndarray                   # (n,) arm configuration at reset
    site: int                          # end-effector site id
    kinematics: Kinematics             # IK on the merged model (its own MjData)
    camera: str | None                 # the wrist camera's name in the merged model

    @property
    def name(self) -> str:
        return self.description.name

    def set_home(self, model, data) -> None:
        """Arm at home, gripper open, servos holding there (qpos and ctrl)."""
        data.qpos[self.arm_qpos] = self.home
        data.ctrl[self.arm_actuators] = self.home
        data.ctrl[self.gripper_actuators] = self.gripper_open
        for adr, act in zip(self.gripper_qpos, self.gripper_actuators):
            joint = int(np.flatnonzero(model.jnt_qposadr == adr)[0])
            data.qpos[adr] = model.jnt_range[joint, 1] if model.jnt_limited[joint] else 0.0

    def gripper(self, closed: float) -> np.ndarray:
        """(a,) gripper control for ``closed`` in [0, 1] (0 open, 1 closed)."""
        closed = float(np.clip(closed, 0.0, 1.0))
        return (1.0 - closed) * self.gripper_open + closed * self.gripper_closed

    def arm_q(self, data) -> np.ndarray:
        return data.qpos[self.arm_qpos].copy()

    def end_effector(self, data) -> tuple[np.ndarray, np.ndarray]:
        """Site position (3,) and rotation (3, 3) in the current state."""
        return data.site_xpos[self.site].copy(), data.site_xmat[self.site].reshape(3, 3).copy()

    def opening_axis(self, model, data) -> np.ndarray:
        """(3,) unit axis, in the site's frame, along which the gripper opens (the first gripper
        joint's slide axis; the site's y when the robot has no gripper joint)."""
        if not len(self.gripper_qpos):
            return np.array([0.0, 1.0, 0.0])
        joint = int(np.flatnonzero(model.jnt_qposadr == self.gripper_qpos[0])[0])
        axis = data.xaxis[joint]
        return data.site_xmat[self.site].reshape(3, 3).T @ axis

    def record(self) -> dict:
        return {"model": self.config.model, "name": self.name, "base": self.placement.record(),
                "end_effector": PREFIX + self.description.end_effector, "camera": self.camera}


def _base(config: RobotConfig, kinematics: Kinematics, home, floor, supports, centres, low, high
          ) -> tuple[Base, str, str]:
    if config.base is not None:
        x, y, z, yaw = config.base
        return Base(np.array([x, y, z], np.float64), float(np.radians(yaw))), "given", "given"
    radius = float(np.linalg.norm(kinematics.forward(home)[0][:2]))
    solve = kinematics.solve

    def ok(r: float) -> bool:
        return all(solve([r, 0.0, h], place.TOP_DOWN, q0=home, iterations=REACH_ITERATIONS).converged
                   for h in (place.GRASP_HEIGHT, place.GRASP_HEIGHT + place.APPROACH))

    band = (0.0, 0.0)
    if ok(radius):
        band = (_bisect(ok, radius, 0.05), _bisect(ok, radius, 2.0))
    base, support = place.default_base(floor, supports, centres, band, low, high)
    return base, support, "default"


def _bisect(ok, inside: float, outside: float, tol: float = 0.01) -> float:
    """The last radius from ``inside`` towards ``outside`` where ``ok`` holds (to ``tol``)."""
    while abs(outside - inside) > tol:
        middle = 0.5 * (inside + outside)
        inside, outside = (middle, outside) if ok(middle) else (inside, middle)
    return inside


def merge_robot(spec, config: RobotConfig, where: Path, objects: dict[int, str]):
    """Attach ``config``'s robot to the scene ``spec`` (edited in place); returns the compiled
    model and the ``Robot``. ``objects``: object id → body name (the reach is checked for each);
    ``where`` (the scene file) names bad input in its one-line error."""
    import mujoco

    scene = spec.compile()
    data = mujoco.MjData(scene)
    mujoco.mj_forward(scene, data)
    floor, supports = place.scene_supports(scene, data)
    centres = place.object_centres(scene, data, [scene.body(name).id for name in objects.values()])

    robot, description = robot_spec(config.model)
    if config.end_effector is not None:
        description = dataclasses.replace(description, end_effector=config.end_effector)
    alone = robot.compile()
    if config.end_effector is not None and config.end_effector not in [alone.site(i).name for i in range(alone.nsite)]:
        raise SceneInputError(None, f"robot {config.model}: site '{config.end_effector}'", "missing from the model")
    low, high = footprint(alone, description)
    reach = Kinematics(alone, description.end_effector, description.arm_joints)
    home = np.asarray(description.home, np.float64)
    base, support, source = _base(config, reach, home, floor, supports, centres, low, high)

    attach_robot(spec, robot, description, base, floor, config.wrist_camera, config.wrist_fovy)
    try:
        model = spec.compile()
    except Exception as err:  # noqa: BLE001
        raise SceneInputError(where, "robot", f"MuJoCo cannot compile the scene with it: {' '.join(str(err).split())}") from None

    mount = model.body(MOUNT).id
    bodies = (mount,) + tuple(b for b in range(model.nbody) if model.body(b).name.startswith(PREFIX))
    ids = lambda kind, names: np.array([model.__getattribute__(kind)(PREFIX + n).id for n in names], np.int64)  # noqa: E731
    joints, grippers = ids("joint", description.arm_joints), ids("joint", description.gripper_joints)
    gripper_actuators = ids("actuator", description.gripper_actuators)
    ranges = model.actuator_ctrlrange[gripper_actuators].reshape(-1, 2)
    handle = Robot(
        config=config, description=description,
        placement=place.Placement(base, support, (), (), source),
        bodies=bodies, arm_qpos=model.jnt_qposadr[joints].copy(), arm_dofs=model.jnt_dofadr[joints].copy(),
        arm_actuators=ids("actuator", description.arm_actuators),
        gripper_qpos=model.jnt_qposadr[grippers].copy(), gripper_actuators=gripper_actuators,
        gripper_open=ranges[:, 1].copy(), gripper_closed=ranges[:, 0].copy(), home=home,
        site=model.site(PREFIX + description.end_effector).id,
        kinematics=Kinematics(model, PREFIX + description.end_effector,
                              tuple(PREFIX + j for j in description.arm_joints)),
        camera=PREFIX + WRIST_CAMERA if config.wrist_camera else None)

    data = mujoco.MjData(model)
    mujoco.mj_resetData(model, data)
    handle.set_home(model, data)
    mujoco.mj_forward(model, data)
    place.check_clear(model, data, set(bodies), where, base)
    ok = place.reachable(reach, home, base, centres) if len(centres) else np.zeros(0, bool)
    reached = tuple(i for i, r in zip(objects, ok) if r)
    missed = tuple(i for i, r in zip(objects, ok) if not r)
    return model, dataclasses.replace(handle, placement=place.Placement(base, support, reached, missed, source))
