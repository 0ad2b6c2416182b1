"""The viewer's live simulation: one ``Environment`` stepped in real time, shot and dragged.

Everything here is plain Python around ``phirie_jax.interact.environment.Environment`` (MuJoCo C);
the browser side (``view.server``) calls it from viser's callback threads and from its own
update thread, so every access to the simulator holds ``lock``.

* play / pause / reset: ``advance(wall_seconds)`` steps while playing, ``reset`` returns to t = 0;
* shoot: a ray (the viewer's click) cast against the collision geometry (``Environment.cast``);
  the first object hit gets an impulse mass × speed along the ray at the hit point
  (``Environment.apply_impulse``), as ``Environment.shoot`` does for a camera pixel;
* drag: a critically damped spring pulls the grabbed point of the body towards the pointer —
  force m (k (target − p) − 2√k ṗ), clamped to m × ``drag_max_acceleration``, applied at the
  point through ``xfrc_applied`` (force and torque about the body's centre of mass);
* node motions: each object's S_i(t) S_i(0)⁻¹ from ``Environment.placements`` (``scene.node_motion``).
"""

from __future__ import annotations

import dataclasses
import threading

import mujoco
import numpy as np

from phirie_jax.interact.environment import Environment
from phirie_jax.rotations import pose_matrix
from phirie_jax.view.config import ViewConfig
from phirie_jax.view.scene import node_motion


@dataclasses.dataclass(frozen=True)
class Grab:
    """A drag in progress: the grabbed point in the body frame and where the pointer is."""

    local: np.ndarray    # (3,) body frame
    target: np.ndarray   # (3,) world


class LiveScene:
    """A simulated environment as the viewer drives it (module docstring)."""

    def __init__(self, env: Environment, config: ViewConfig = ViewConfig()):
        self.env = env
        self.config = config
        self.lock = threading.RLock()
        self.playing = config.playing
        self.grabs: dict[int, Grab] = {}
        self.shots: list[dict] = []   # what every shot hit, in order
        with self.lock:
            env.reset()
            self.placements0 = env.placements()   # S_i(0)

    @property
    def object_ids(self) -> list[int]:
        return [o.id for o in self.env.objects]

    # --- time ---------------------------------------------------------------------------

    def advance(self, wall_seconds: float) -> int:
        """Step the simulator by ``wall_seconds`` × ``realtime`` while playing (at most
        ``max_substeps`` steps); returns the number of steps taken."""
        if not self.playing:
            return 0
        steps = int(round(wall_seconds * self.config.realtime / self.env.timestep))
        steps = min(max(steps, 0), self.config.max_substeps)
        with self.lock:
            if not self.grabs:
                self.env.step(steps)
                return steps
            for _ in range(steps):  # the spring follows the body: recomputed every step
                self._apply_grabs()
                self.env.step(1)
            self._apply_grabs()
        return steps

    def reset(self) -> None:
        with self.lock:
            self.grabs.clear()
            self.env.data.xfrc_applied[:] = 0.0
            self.env.reset()

    @property
    def time(self) -> float:
        return self.env.time

    def motions(self) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """(object id, wxyz (4,), position (3,)) of every object node: S_i(t) S_i(0)⁻¹."""
        with self.lock:
            placements = self.env.placements()
        return [(o.id, *node_motion(p, p0)) for o, p, p0 in zip(self.env.objects, placements, self.placements0)]

    # --- interactions -------------------------------------------------------------------

    def shoot(self, origin, direction, speed: float | None = None) -> dict:
        """Hit the first object along the ray (world origin (3,), direction (3,)) with
        mass × speed along it; returns ``{"hit": id or None, "point": ...}``."""
        direction = np.asarray(direction, np.float64)
        direction = direction / np.linalg.norm(direction)
        speed = self.config.shot_speed if speed is None else speed
        with self.lock:
            object_id, point = self.env.cast(np.asarray(origin, np.float64), direction)
            if object_id is None:
                shot = {"hit": None, "point": None if point is None else point.tolist()}
                self.shots.append(shot)
                return shot
            mass = float(self.env.model.body_subtreemass[self.env.object(object_id).body_id])
            self.env.apply_impulse(object_id, point, mass * speed * direction)
        shot = {"hit": object_id, "point": point.tolist(), "impulse": (mass * speed * direction).tolist()}
        self.shots.append(shot)
        return shot

    def grab(self, object_id: int, point) -> None:
        """Start dragging ``object_id`` by the world point (3,) on it."""
        with self.lock:
            pose = self._body_pose(object_id)
            local = np.linalg.solve(pose, np.append(np.asarray(point, np.float64), 1.0))[:3]
            self.grabs[object_id] = Grab(local, np.asarray(point, np.float64))

    def drag_to(self, object_id: int, target) -> None:
        """Move the pointer of a drag in progress to the world point (3,)."""
        with self.lock:
            if object_id in self.grabs:
                self.grabs[object_id] = dataclasses.replace(self.grabs[object_id], target=np.asarray(target, np.float64))

    def release(self, object_id: int) -> None:
        with self.lock:
            if self.grabs.pop(object_id, None) is not None:
                self.env.data.xfrc_applied[self.env.object(object_id).body_id] = 0.0

    # --- internals ----------------------------------------------------------------------

    def _body_pose(self, object_id: int) -> np.ndarray:
        body = self.env.object(object_id).body_id
        return pose_matrix(self.env.data.xpos[body], self.env.data.xquat[body])

    def drag_wrench(self, object_id: int) -> np.ndarray:
        """(6,) force and torque (about the centre of mass) the drag of ``object_id`` applies now."""
        grab = self.grabs[object_id]
        model, data = self.env.model, self.env.data
        body = self.env.object(object_id).body_id
        point = (self._body_pose(object_id) @ np.append(grab.local, 1.0))[:3]
        jacp = np.zeros((3, model.nv))
        mujoco.mj_jac(model, data, jacp, None, point, body)
        velocity = jacp @ data.qvel
        k = self.config.drag_stiffness
        acceleration = k * (grab.target - point) - 2.0 * np.sqrt(k) * velocity
        norm = np.linalg.norm(acceleration)
        if norm > self.config.drag_max_acceleration:
            acceleration *= self.config.drag_max_acceleration / norm
        force = float(model.body_subtreemass[body]) * acceleration
        return np.concatenate([force, np.cross(point - data.xipos[body], force)])

    def _apply_grabs(self) -> None:
        mujoco.mj_kinematics(self.env.model, self.env.data)  # poses of the current qpos
        mujoco.mj_comPos(self.env.model, self.env.data)       # the Jacobian's reference frames
        for object_id in self.grabs:
            self.env.data.xfrc_applied[self.env.object(object_id).body_id] = self.drag_wrench(object_id)
