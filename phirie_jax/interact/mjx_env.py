"""A pure-functional MJX environment in the MuJoCo Playground style: ``reset(rng)`` and
``step(state, action)``, jit- and vmap-able, observations with rendered images.

``MjxPickPlace(env, object_id, goal)`` takes a single ``Environment`` with a robot and puts its
model on the device (objects colliding through one convex hull each, as ``BatchedEnvironment``
does, or their exported parts). A ``State`` holds the MJX data, the observation, reward, done
and ``info`` (the episode's rng, step count and the object's start rotation).

* ``reset(rng)``: the home state with every object moved within ``placement_range`` of its
  converted place at a random yaw: ``CANDIDATES`` draws per object, the first whose footprint
  circle clears the objects placed before it (a fixed-size rejection sampler, so it traces);
* ``step(state, action)``: ``action`` is the control vector (nu,) in the actuators' own units
  (the robot's servo targets and gripper), held for ``substeps`` MJX steps;
* observation: ``joint_pos`` / ``joint_vel`` of the arm and gripper, ``object_poses`` (K, 7) and,
  with cameras, ``rgb`` (C, H, W, 3) in [0, 1]: the scene's Gaussians placed by this world's
  body poses (background, objects and robot links, ``compose_scene``) rasterized from the
  capture cameras and the body-attached cameras posed by this world's state (the wrist);
* reward −(object's centre to goal, m); done when it is within 3 cm and upright.

Rasterization inside jit needs static capacities: they are fitted once on the initial scene
(``Renderer.fitted_config``) with ``CAPACITY_MARGIN``; ``info["render_overflow"]`` reports a
frame that needed more.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from kernels.gaussians import quat_to_rotmat
from kernels.pytree import pytree_dataclass
from phirie_jax.interact.environment import Environment, compose_scene
from phirie_jax.interact.mjx_model import CollisionModel, body_frame_vertices, hull_collision_spec, multi_part
from phirie_jax.interact.robot import script

CANDIDATES = 32            # placement draws per object at reset
CAPACITY_MARGIN = 2        # × the tile intersections the initial scene needed, per camera
PLACEMENT_GAP = 0.01       # m between footprint circles


@pytree_dataclass
class State:
    data: Any                  # mjx.Data of one world
    obs: dict                  # see the module docstring
    reward: jax.Array          # ()
    done: jax.Array            # () bool
    info: dict                 # rng (2,), step (), start_rotation (3, 3), render_overflow ()


class MjxPickPlace:
    """Move ``object_id`` to ``goal`` (x, y) in batched MJX worlds (module docstring)."""

    def __init__(self, env: Environment, object_id: int, goal, cameras: tuple = (), width: int = 32,
                 control_hz: float = script.CONTROL_HZ, placement_range: float = 0.05,
                 collision: CollisionModel = "hull", background=(0.62, 0.66, 0.72)):
        import mujoco
        from mujoco import mjx

        if env.robot is None:
            raise ValueError("MjxPickPlace needs an environment with a robot (Environment.load(..., robot=...))")
        self.env = env
        merged = [o.body for o in env.objects if o.id is not None and collision == "hull"
                  and multi_part(env.model, o.body_id)]
        self.mj_model = hull_collision_spec(env.spec(), env.model, merged).compile() if merged else env.model
        self.model = mjx.put_model(self.mj_model)
        data = mujoco.MjData(self.mj_model)
        env.robot.set_home(self.mj_model, data)
        mujoco.mj_forward(self.mj_model, data)
        self._data0 = mjx.put_data(self.mj_model, data)
        self.substeps = script.substeps(env.timestep, control_hz)
        self.object_id, self.goal = object_id, jnp.asarray(np.asarray(goal, np.float64)[:2], jnp.float32)
        objects = [o for o in env.objects if o.id is not None]
        self.object_bodies = np.array([o.body_id for o in objects])
        self.target = [o.id for o in objects].index(object_id)
        self.free_qpos = np.array([self.mj_model.jnt_qposadr[self.mj_model.body_jntadr[b]] for b in self.object_bodies])
        robot = env.robot
        self.joints = np.concatenate([robot.arm_qpos, robot.gripper_qpos])
        self.dofs = np.array([self.mj_model.jnt_dofadr[np.flatnonzero(self.mj_model.jnt_qposadr == a)[0]]
                              for a in self.joints])
        centres, radii = [], []
        for b in self.object_bodies:
            verts = body_frame_vertices(self.mj_model, b)
            lo, hi = verts.min(0), verts.max(0)
            centres.append(0.5 * (lo + hi))
            radii.append(float(np.max(np.linalg.norm((verts - 0.5 * (lo + hi))[:, :2], axis=1))))
        self.body_centres = jnp.asarray(np.asarray(centres), jnp.float32)   # (K, 3) body frame
        self.radii = jnp.asarray(radii, jnp.float32)
        self.placement_range = float(placement_range)
        self._setup_rendering(cameras, width, background)

    # --- rendering setup (host, once) ------------------------------------------------------

    def _setup_rendering(self, cameras, width: int, background) -> None:
        from phirie_jax.render import Renderer, gaussian_bucket, pad_gaussians

        env = self.env
        self.cameras = tuple(cameras)
        self.background = jnp.asarray(background, jnp.float32)
        self.attached_bodies = jnp.asarray([o.body_id for o in env.objects], jnp.int32)
        pose0 = np.stack([o.pose0 for o in env.objects])
        self.inverse_t0_pose0 = jnp.asarray(np.linalg.inv(env.body_poses()) @ pose0, jnp.float32)
        if not self.cameras:
            return
        records = [env.camera(c) for c in self.cameras]
        records = [c.scaled(width / c.width) for c in records]
        if len({(c.width, c.height) for c in records}) != 1:
            raise ValueError("MjxPickPlace cameras must share one aspect ratio")
        self.size = (records[0].width, records[0].height)
        self.mjcf_cameras = [(k, self.mj_model.camera(env.model.camera(c.name).id).id) for k, c in enumerate(records)
                             if not isinstance(self.cameras[k], int)]
        self.Ks = jnp.asarray(np.stack([c.K for c in records]), jnp.float32)
        self.w2cs = jnp.asarray(np.stack([c.world_to_camera for c in records]), jnp.float32)
        scene = env.gaussians()
        self.bucket = gaussian_bucket(scene.num)
        renderer = Renderer()
        needed = max(renderer.fitted_config(pad_gaussians(scene, self.bucket), c).capacity for c in records)
        fitted = renderer.last_config
        self.raster = dataclasses.replace(fitted, capacity=CAPACITY_MARGIN * needed,
                                          tile_capacity=max(fitted.tile_capacity, 1))

    # --- the functional API ---------------------------------------------------------------

    def reset(self, rng) -> State:
        from mujoco import mjx

        rng, key = jax.random.split(rng)
        data = self._placed(self._data0, key)
        data = mjx.forward(self.model, data)
        rotation = data.xmat[self.object_bodies[self.target]]
        info = {"rng": rng, "step": jnp.zeros((), jnp.int32), "start_rotation": rotation,
                "render_overflow": jnp.zeros((), bool)}
        obs, overflow = self._observe(data)
        reward, done = self._reward(data, rotation)
        return State(data, obs, reward, done, {**info, "render_overflow": overflow})

    def step(self, state: State, action) -> State:
        from mujoco import mjx

        data = state.data.replace(ctrl=jnp.asarray(action, state.data.ctrl.dtype))
        data = jax.lax.fori_loop(0, self.substeps, lambda _, d: mjx.step(self.model, d), data)
        obs, overflow = self._observe(data)
        reward, done = self._reward(data, state.info["start_rotation"])
        info = {**state.info, "step": state.info["step"] + 1, "render_overflow": overflow}
        return State(data, obs, reward, done, info)

    # --- pieces ---------------------------------------------------------------------------

    def _placed(self, data, key):
        """Objects moved within range at random yaws, footprints clear (module docstring)."""
        k = len(self.object_bodies)
        shift_key, yaw_key = jax.random.split(key)
        shifts = jax.random.uniform(shift_key, (k, CANDIDATES, 2), minval=-1.0, maxval=1.0) * self.placement_range
        yaws = jax.random.uniform(yaw_key, (k, CANDIDATES), minval=-jnp.pi, maxval=jnp.pi)
        qpos = data.qpos
        rot0 = quat_to_rotmat(qpos[self.free_qpos[:, None] + np.arange(3, 7)])          # (K, 3, 3)
        centre0 = qpos[self.free_qpos[:, None] + np.arange(3)] + jnp.einsum("kij,kj->ki", rot0, self.body_centres)
        chosen = []
        for i in range(k):
            xy = centre0[i, :2] + shifts[i]                                                    # (C, 2)
            clear = jnp.ones(CANDIDATES, bool)
            for j, (other, _) in enumerate(chosen):
                clear &= jnp.linalg.norm(xy - other, axis=1) > self.radii[i] + self.radii[j] + PLACEMENT_GAP
            pick = jnp.where(clear.any(), jnp.argmax(clear), 0)
            chosen.append((jnp.where(clear.any(), xy[pick], centre0[i, :2]), jnp.where(clear.any(), yaws[i, pick], 0.0)))
        for i, (xy, yaw) in enumerate(chosen):
            c, s = jnp.cos(yaw), jnp.sin(yaw)
            turn = jnp.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], rot0.dtype)
            rot = turn @ rot0[i]
            centre = jnp.concatenate([xy, centre0[i, 2:]])
            position = centre - rot @ self.body_centres[i]
            half = yaw / 2
            quat = _quat_multiply(jnp.array([jnp.cos(half), 0.0, 0.0, jnp.sin(half)]), qpos[self.free_qpos[i] + 3:self.free_qpos[i] + 7])
            qpos = qpos.at[self.free_qpos[i]:self.free_qpos[i] + 3].set(position).at[self.free_qpos[i] + 3:self.free_qpos[i] + 7].set(quat)
        return data.replace(qpos=qpos)

    def _reward(self, data, start_rotation):
        body = self.object_bodies[self.target]
        centre = data.xpos[body] + data.xmat[body] @ self.body_centres[self.target]
        distance = jnp.linalg.norm(centre[:2] - self.goal)
        tilt = jnp.degrees(jnp.arccos(jnp.clip((data.xmat[body] @ start_rotation.T)[2, 2], -1.0, 1.0)))
        return -distance, (distance <= script.SUCCESS_DISTANCE) & (tilt <= script.UPRIGHT_DEG)

    def _observe(self, data) -> tuple[dict, jax.Array]:
        k = len(self.object_bodies)
        obs = {"joint_pos": data.qpos[self.joints], "joint_vel": data.qvel[self.dofs],
               "object_poses": jnp.concatenate([data.xpos[self.object_bodies], data.xquat[self.object_bodies]],
                                               axis=1).reshape(k, 7)}
        if not self.cameras:
            return obs, jnp.zeros((), bool)
        from kernels.raster import render_batch
        from phirie_jax.render import pad_gaussians

        rot = quat_to_rotmat(data.xquat[self.attached_bodies].astype(jnp.float32))
        pose = jnp.concatenate([rot, data.xpos[self.attached_bodies][..., None].astype(jnp.float32)], axis=-1)
        pose = jnp.concatenate([pose, jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0]), pose.shape[:-2] + (1, 4))], axis=-2)
        scene = compose_scene(self.env.background, self.env.object_gaussians, self.env.body_index,
                              pose @ self.inverse_t0_pose0)
        w2cs = self.w2cs
        for k_cam, cam in self.mjcf_cameras:  # body-attached cameras: posed by this world
            rot_cv = data.cam_xmat[cam].astype(jnp.float32) @ jnp.diag(jnp.array([1.0, -1.0, -1.0]))
            w2c = jnp.eye(4).at[:3, :3].set(rot_cv.T).at[:3, 3].set(-rot_cv.T @ data.cam_xpos[cam].astype(jnp.float32))
            w2cs = w2cs.at[k_cam].set(w2c)
        out = render_batch(pad_gaussians(scene, self.bucket), self.Ks, w2cs, width=self.size[0], height=self.size[1],
                           background=self.background, config=self.raster)
        return {**obs, "rgb": out.rgb}, jnp.any(out.overflow)


def _quat_multiply(a, b):
    from kernels.gaussians import quat_multiply

    return quat_multiply(a, b)
