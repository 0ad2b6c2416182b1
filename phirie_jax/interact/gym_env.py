"""A Gymnasium environment on a converted scene with a robot: move one object to a goal.

``PickPlaceEnv(out_dir, GymConfig(...))`` wraps ``Environment.load(out_dir, robot=...)``:

* observation (``gymnasium.spaces.Dict``): ``rgb`` — one uint8 image (H, W, 3) per camera
  (capture cameras by index, MJCF cameras by name, e.g. the robot's ``wrist``), optional
  ``depth`` (H, W) in metres, ``joint_pos`` / ``joint_vel`` of the arm and gripper joints,
  ``object_poses`` (K, 7) position and wxyz quaternion of every object, and the ``goal`` (x, y);
* action (``Box(-1, 1)``): ``"joint"`` — arm servo targets scaled to their control ranges, then
  the gripper (−1 open … 1 closed); ``"ee_delta"`` — the end effector's move (dx, dy, dz in
  units of ``ee_step``, yaw in units of ``yaw_step``) solved by damped least squares, then the
  gripper;
* reward −(distance of the object's centre to the goal); terminated when the object stands at
  the goal (``robot.script.outcome``: within 3 cm, upright); truncated after ``max_steps``;
* ``reset(seed=...)`` puts the objects back and moves each within ``placement_range`` of where
  it was converted, at a random yaw, rejecting placements whose footprints overlap another's or
  leave the support; the capture cameras are jittered by ``camera_jitter`` (m, degrees).
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import gymnasium
import numpy as np
from gymnasium import spaces

from phirie_jax.interact.environment import Environment
from phirie_jax.interact.robot import script
from phirie_jax.interact.robot.config import RobotConfig
from phirie_jax.interact.robot.placement import object_centres, scene_supports
from phirie_jax.ranges import Choice, check_ranges
from phirie_jax.rotations import rotvec_to_matrix, yaw_matrix
from phirie_jax.types import Camera

Action = Literal["joint", "ee_delta"]   # joint targets, or an end-effector step (``GymConfig``)
PLACEMENT_TRIES = 200
PLACEMENT_GAP = 0.01       # m between sampled footprints


@dataclasses.dataclass(frozen=True)
class GymConfig:
    """Attributes:
        robot: the robot (``RobotConfig``).
        object_id: the object to move (None: the first the gripper fits and the arm reaches).
        goal: (x, y) of the goal (None: 15 cm from the object's converted place, free and reachable).
        action: "joint" or "ee_delta" (module docstring).
        cameras: the observed cameras: capture camera indices or MJCF camera names.
        width: observed image width, pixels (heights follow each camera's aspect).
        depth: also observe depth images.
        control_hz: actions per simulated second.
        max_steps: steps before truncation.
        placement_range: m, how far ``reset`` moves each object from its converted place.
        camera_jitter: (m, degrees) of the capture cameras' random offset at ``reset``.
        ee_step: m per unit of an "ee_delta" action; yaw_step: rad per unit.
    """

    robot: RobotConfig = RobotConfig()
    object_id: int | None = None
    goal: tuple[float, float] | None = None
    action: Action = "joint"
    cameras: tuple[int | str, ...] = (0, "wrist")
    width: int = 64
    depth: bool = False
    control_hz: float = 20.0
    max_steps: int = 200
    placement_range: float = 0.05
    camera_jitter: tuple[float, float] = (0.01, 1.0)
    ee_step: float = 0.02
    yaw_step: float = 0.1

    def __post_init__(self):
        check_ranges(self, {"action": Choice.of(Action)})


class PickPlaceEnv(gymnasium.Env):
    """Move one object of a converted scene to a goal with the robot (module docstring)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(self, out_dir, config: GymConfig = GymConfig(), render_mode: str | None = "rgb_array"):
        self.config = config
        self.render_mode = render_mode
        self.env = Environment.load(out_dir, robot=config.robot)
        robot = self.env.robot
        ids = [o.id for o in self.env.objects if o.id is not None]
        self.object_ids = ids
        self.object_id = config.object_id if config.object_id is not None else next(
            i for i in ids if i in robot.placement.reachable and script.grasp_for(self.env, i).fits)
        self.goal = np.asarray(config.goal if config.goal is not None else _default_goal(self.env, self.object_id))
        self.substeps = script.substeps(self.env.timestep, config.control_hz)
        self.home_pose = [o.pose0.copy() for o in self.env.objects if o.id is not None]
        self.joints = np.concatenate([robot.arm_qpos, robot.gripper_qpos])
        self.dofs = np.array([self.env.model.jnt_dofadr[np.flatnonzero(self.env.model.jnt_qposadr == a)[0]]
                              for a in self.joints])
        self.cameras = {str(c): c for c in config.cameras}
        self._scene_cameras = {}
        shapes = {name: self._camera(name).height for name in self.cameras}
        image = {n: spaces.Box(0, 255, (h, config.width, 3), np.uint8) for n, h in shapes.items()}
        observation = {"rgb": spaces.Dict(image),
                       "joint_pos": spaces.Box(-np.inf, np.inf, (len(self.joints),), np.float64),
                       "joint_vel": spaces.Box(-np.inf, np.inf, (len(self.joints),), np.float64),
                       "object_poses": spaces.Box(-np.inf, np.inf, (len(ids), 7), np.float64),
                       "goal": spaces.Box(-np.inf, np.inf, (2,), np.float64)}
        if config.depth:
            observation["depth"] = spaces.Dict({n: spaces.Box(0.0, np.inf, (h, config.width), np.float32)
                                                for n, h in shapes.items()})
        self.observation_space = spaces.Dict(observation)
        size = len(robot.arm_actuators) + 1 if config.action == "joint" else 5
        self.action_space = spaces.Box(-1.0, 1.0, (size,), np.float32)
        self._steps = 0
        self._start_rotation = np.eye(3)

    # --- gymnasium API -------------------------------------------------------------------

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        env = self.env
        env.reset()
        self._place_objects()
        self._jitter_cameras()
        self._steps = 0
        body = env.object(self.object_id).body_id
        self._start_rotation = env.data.xmat[body].reshape(3, 3).copy()
        return self._observation(), self._info()

    def step(self, action):
        env, robot = self.env, self.env.robot
        action = np.clip(np.asarray(action, np.float64), -1.0, 1.0)
        if self.config.action == "joint":
            ranges = env.model.actuator_ctrlrange[robot.arm_actuators]
            env.data.ctrl[robot.arm_actuators] = ranges[:, 0] + 0.5 * (action[:-1] + 1.0) * (ranges[:, 1] - ranges[:, 0])
        else:
            env.data.ctrl[robot.arm_actuators] = self._ee_targets(action[:4])
        env.data.ctrl[robot.gripper_actuators] = robot.gripper(0.5 * (action[-1] + 1.0))
        env.step(self.substeps)
        self._steps += 1
        info = self._info()
        return (self._observation(), -info["distance_m"], bool(info["success"]),
                self._steps >= self.config.max_steps, info)

    def render(self):
        name = next(iter(self.cameras), None)
        return None if name is None else self._rendered(name)[0]

    # --- pieces ----------------------------------------------------------------------------

    def _camera(self, name: str) -> Camera:
        key = self.cameras[name]
        cam = self._scene_cameras.get(name) or self.env.camera(key)
        return cam.scaled(self.config.width / cam.width)

    def _rendered(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """uint8 rgb (H, W, 3) and float32 depth (H, W) from one observed camera."""
        out = self.env.render(self._camera(name))
        return (np.clip(np.round(np.asarray(out.rgb) * 255), 0, 255).astype(np.uint8),
                np.asarray(out.depth, np.float32))

    def _observation(self) -> dict:
        env = self.env
        rgb, depth = {}, {}
        for name in self.cameras:
            rgb[name], depth[name] = self._rendered(name)
        poses = []
        for i in self.object_ids:
            body = env.object(i).body_id
            poses.append(np.concatenate([env.data.xpos[body], env.data.xquat[body]]))
        obs = {"rgb": rgb, "joint_pos": env.data.qpos[self.joints].copy(), "joint_vel": env.data.qvel[self.dofs].copy(),
               "object_poses": np.asarray(poses).reshape(len(self.object_ids), 7), "goal": self.goal.astype(np.float64)}
        if self.config.depth:
            obs["depth"] = depth
        return obs

    def _info(self) -> dict:
        return script.outcome(self.env, self.object_id, self.goal, self._start_rotation)

    def _ee_targets(self, delta: np.ndarray) -> np.ndarray:
        """Arm servo targets moving the end effector by ``delta`` (dx, dy, dz, dyaw in action units)."""
        robot = self.env.robot
        q = self.env.data.ctrl[robot.arm_actuators].copy()
        position, rotation = robot.kinematics.forward(q)
        yaw = rotvec_to_matrix([0.0, 0.0, self.config.yaw_step * delta[3]])
        result = robot.kinematics.solve(position + self.config.ee_step * delta[:3], yaw @ rotation, q0=q, iterations=10)
        return result.q

    def _place_objects(self) -> None:
        """Each object within ``placement_range`` of its converted place at a random yaw, its
        footprint clear of the others' and inside its support (rejection sampling)."""
        env, rng = self.env, self.np_random
        _, supports = scene_supports(env.model, env.data)
        placed: list[tuple[np.ndarray, float]] = []
        for object_id, pose0 in zip(self.object_ids, self.home_pose):
            body = env.object(object_id).body_id
            centre = object_centres(env.model, env.data, [body])[0]
            radius = _footprint_radius(env, body, centre)
            for _ in range(PLACEMENT_TRIES):
                shift = rng.uniform(-1.0, 1.0, 2) * self.config.placement_range
                xy = centre[:2] + shift
                clear = all(np.linalg.norm(xy - c) > radius + r + PLACEMENT_GAP for c, r in placed)
                if clear and _on_support(supports, xy, radius, centre[2]):
                    break
            else:
                xy, shift = centre[:2], np.zeros(2)
            placed.append((xy, radius))
            turn = np.eye(4)
            turn[:3, :3] = yaw_matrix(rng.uniform(-np.pi, np.pi))
            turn[:3, 3] = np.array([*centre[:2], 0.0]) - turn[:3, :3] @ np.array([*centre[:2], 0.0])
            turn[:2, 3] += shift
            current = np.eye(4)
            current[:3, :3], current[:3, 3] = env.data.xmat[body].reshape(3, 3), env.data.xpos[body]
            env.place(object_id, pose=turn @ current)

    def _jitter_cameras(self) -> None:
        metres, degrees = self.config.camera_jitter
        self._scene_cameras = {}
        for name, key in self.cameras.items():
            if not isinstance(key, int):
                continue
            cam = self.env.camera(key)
            offset = np.eye(4)
            offset[:3, :3] = rotvec_to_matrix(np.radians(degrees) * self.np_random.uniform(-1, 1, 3))
            offset[:3, 3] = metres * self.np_random.uniform(-1, 1, 3)
            self._scene_cameras[name] = dataclasses.replace(cam, world_to_camera=offset @ cam.world_to_camera)


def _default_goal(env: Environment, object_id: int) -> np.ndarray:
    from phirie_jax.interact.rollout import free_goal

    return free_goal(env, object_id)


def _footprint_radius(env: Environment, body: int, centre: np.ndarray) -> float:
    from phirie_jax.interact.mjx_model import body_frame_vertices

    verts = body_frame_vertices(env.model, body) @ env.data.xmat[body].reshape(3, 3).T + env.data.xpos[body]
    return float(np.max(np.linalg.norm(verts[:, :2] - centre[:2], axis=1)))


def _on_support(supports, xy: np.ndarray, radius: float, top: float) -> bool:
    for s in supports:
        local = s.axes @ (np.array([*xy, s.centre[2]]) - s.centre)
        if s.centre[2] < top and np.all(np.abs(local) + radius <= s.half):
            return True
    return not supports
