"""A pure-functional MJX environment in the MuJoCo Playground style: ``reset(rng)`` and
``step(state, action)``, jit- and vmap-able, observations with rendered images.

``MjxPickPlace(env, object_id, goal)`` takes a single ``Environment`` with a robot and puts its
model on the device (``mjx_model``). A ``State`` holds the MJX data, the observation, reward,
done and ``info``: the episode's rng, step count, the task (``target``: the object's index
among the scene's objects, ``goal`` (2,)) and the target's start rotation.

* ``reset(rng, task=None)``: the home state with every object moved within ``placement_range``
  of its converted place at a random yaw: ``CANDIDATES`` draws per object, the first whose
  footprint circle clears the objects placed before it (a fixed-size rejection sampler, so it
  traces). ``task`` (``menv.task(object_id, goal)``; default the constructor's) is data, not
  part of the program: one compiled reset and step serve every object and goal;
* ``step(state, action)``: ``action`` is the control vector (nu,) in the actuators' own units
  (the robot's servo targets and gripper), held for ``substeps`` MJX steps;
* observation: ``joint_pos`` / ``joint_vel`` of the arm and gripper, ``object_poses`` (K, 7),
  ``goal`` (2,) and, with cameras, ``rgb`` (C, H, W, 3) in [0, 1]: the scene's Gaussians placed
  by this world's body poses (background, objects and robot links, ``compose_scene``)
  rasterized from the capture cameras and the body-attached cameras posed by this world's state
  (the wrist);
* reward −(object's centre to goal, m); done when it is within 3 cm and upright.

The MJX model (``mjx_model``) differs from the single environment's in contacts only: the
robot collides through one box per finger (``robot.collision``) and each object through one
convex hull of at most ``HULL_VERTICES`` (``collision="hull"``, ``interact.mjx_model``), except
that the parts of ``object_id``, when it has several, meet the pads (a grip on its real shape):
MJX traces a few dozen collision functions instead of hundreds. The task's target can change
per episode (``task``); the grip is ``object_id``'s.
Bodies, joints, actuators, masses and inertias are the same, so MuJoCo C runs the same model
for reference (the tests do).

Batching worlds: ``jax.vmap(menv.step)`` on an accelerator. On the CPU, ``over_worlds(menv.step)``
runs the worlds one after another inside the compiled program (``jax.lax.map``): jaxlib 0.10's
batched LAPACK Cholesky (MJX factors the mass matrix, the Newton Hessian and the implicit
integrator's matrix) splits its batch over XLA:CPU's intra-op thread pool and blocks waiting for
the pieces; two such calls at once on a 2-core machine block both threads for good (every thread
asleep in ``ParallelBatchMap``).

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

from kernels.gaussians import quat_multiply, quat_to_rotmat
from kernels.pytree import pytree_dataclass
from phirie_jax.construct.physics.body import is_mounted
from phirie_jax.interact.environment import Environment, compose_scene
from phirie_jax.interact.mjx_model import CollisionModel, body_frame_vertices, hull_collision_spec, multi_part
from phirie_jax.interact.robot import script
from phirie_jax.interact.robot.collision import grip_parts_spec, pad_collision_spec, pad_names

CANDIDATES = 32            # placement draws per object at reset
CAPACITY_MARGIN = 2        # × the tile intersections the initial scene needed, per camera
PLACEMENT_GAP = 0.01       # m between footprint circles
# Vertices of an object's hull in the MJX model. MJX's convex collider mis-handles faces of many
# coplanar vertices (a can's full hull, caps of 32 vertices, is lifted and pushed by the closing
# pads where MuJoCo C's is not); hulls of at most 32 vertices keep every face small.
HULL_VERTICES = 32


@pytree_dataclass
class State:
    data: Any                  # mjx.Data of one world
    obs: dict                  # see the module docstring
    reward: jax.Array          # ()
    done: jax.Array            # () bool
    info: dict                 # rng (2,), step (), target (), goal (2,), start_rotation (3, 3),
                               # render_overflow ()


def mjx_model(env: Environment, collision: CollisionModel = "hull", grasped: int | None = None):
    """The ``mujoco.MjModel`` batched worlds of ``env`` run on MJX (module docstring): the robot
    (when there is one) collides through its finger pads, each object through its hull
    (``"hull"``) or its exported parts (``"parts"``); the ``grasped`` object's parts, not its
    hull, meet the pads when it has several (``robot.collision.grip_parts_spec``)."""
    if collision not in ("hull", "parts"):
        raise ValueError(f"collision {collision!r} (expected 'hull' or 'parts')")
    spec = env.spec()
    if env.robot is not None:
        spec = pad_collision_spec(spec, env.model, env.robot)
    merged = [o.body for o in env.objects if o.id is not None and collision == "hull"
              and mesh_collider(env.model, o.body_id)]
    spec = hull_collision_spec(spec, env.model, merged, max_vertices=HULL_VERTICES)
    held = env.object(grasped) if grasped is not None else None
    if held is not None and env.robot is not None and held.body in merged and multi_part(env.model, held.body_id):
        spec = grip_parts_spec(spec, env.model, held.body, pad_names(env.model, env.robot))
    return spec.compile()


def mesh_collider(model, body_id: int) -> bool:
    """Whether a body collides, and only through mesh geoms (a converted object's parts)."""
    import mujoco

    geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] == body_id
             and (model.geom_contype[g] or model.geom_conaffinity[g])]
    return bool(geoms) and all(model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH for g in geoms)


def over_worlds(fn):
    """``fn`` (one world's ``(state, action)`` → state) applied to a leading world axis: ``jax.vmap``
    on an accelerator, ``jax.lax.map`` on the CPU (module docstring: the LAPACK deadlock)."""
    if jax.default_backend() != "cpu":
        return jax.vmap(fn)
    return lambda *args: jax.lax.map(lambda one: fn(*one), args)


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
        self.mj_model = mjx_model(env, collision, grasped=object_id)
        self.model = mjx.put_model(self.mj_model)
        data = mujoco.MjData(self.mj_model)
        env.robot.set_home(self.mj_model, data)
        mujoco.mj_forward(self.mj_model, data)
        self._data0 = mjx.put_data(self.mj_model, data)
        self.substeps = script.substeps(env.timestep, control_hz)
        objects = [o for o in env.objects if o.id is not None]
        self.object_ids = [o.id for o in objects]
        self.object_bodies = np.array([o.body_id for o in objects])
        self.mounted = [is_mounted(self.mj_model, o.body) for o in objects]   # welded to a wall: left where it is
        self.default_task = self.task(object_id, goal)
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
        self.radii = jnp.asarray(radii, jnp.float32)                          # (K,) footprint circles
        self.placement_range = float(placement_range)
        self._setup_rendering(cameras, width, background)

    # --- sizes, as MuJoCo Playground's ``MjxEnv`` gives them ------------------------------

    @property
    def action_size(self) -> int:
        """Length of ``step``'s action: the model's actuators (arm servos and gripper)."""
        return int(self.mj_model.nu)

    @property
    def observation_size(self) -> dict[str, tuple[int, ...]]:
        """Observation key → its shape in one world (traced, not run: ``jax.eval_shape``)."""
        state = jax.eval_shape(self.reset, jax.random.PRNGKey(0))
        return {key: tuple(value.shape) for key, value in state.obs.items()}

    @property
    def dt(self) -> float:
        """Seconds one ``step`` simulates: ``substeps`` of the model's timestep (the control period)."""
        return self.substeps * float(self.mj_model.opt.timestep)

    def task(self, object_id: int, goal) -> dict:
        """The task as data for ``reset``: ``target`` () int32 (the object's index), ``goal`` (2,)."""
        if object_id not in self.object_ids:
            raise ValueError(f"object {object_id} is not a simulated object (expected one of {self.object_ids})")
        return {"target": jnp.asarray(self.object_ids.index(object_id), jnp.int32),
                "goal": jnp.asarray(np.asarray(goal, np.float64)[:2], jnp.float32)}

    # --- rendering setup (host, once) ------------------------------------------------------

    def _setup_rendering(self, cameras, width: int, background) -> None:
        from phirie_jax.render import Renderer, gaussian_bucket, pad_gaussians

        env = self.env
        self.cameras = tuple(cameras)
        self.background = jnp.asarray(background, jnp.float32)
        self.attached_bodies = jnp.asarray([o.body_id for o in env.objects], jnp.int32)
        # T_i(t)⁻¹ S_i(t) = T_i(0)⁻¹ S_i(0) at any t: the environment may have moved
        self.inverse_t0_pose0 = jnp.asarray(np.linalg.inv(env.body_poses()) @ env.placements(), jnp.float32)
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

    def reset(self, rng, task: dict | None = None) -> State:
        from mujoco import mjx

        task = self.default_task if task is None else task
        rng, key = jax.random.split(rng)
        data = self._placed(self._data0, key)
        # what the observation and reward read depends on positions only; the first step
        # computes the rest (as MuJoCo C's mj_step does), so reset compiles no collision or solver
        for stage in (mjx.kinematics, mjx.com_pos, mjx.camlight):
            data = stage(self.model, data)
        rotation = data.xmat[jnp.asarray(self.object_bodies)[task["target"]]]
        info = {"rng": rng, "step": jnp.zeros((), jnp.int32), "target": task["target"], "goal": task["goal"],
                "start_rotation": rotation}
        obs, overflow = self._observe(data, task["goal"])
        reward, done = self._reward(data, info)
        return State(data, obs, reward, done, {**info, "render_overflow": overflow})

    def step(self, state: State, action) -> State:
        from mujoco import mjx

        data = state.data.replace(ctrl=jnp.asarray(action, state.data.ctrl.dtype))
        data = jax.lax.fori_loop(0, self.substeps, lambda _, d: mjx.step(self.model, d), data)
        obs, overflow = self._observe(data, state.info["goal"])
        reward, done = self._reward(data, state.info)
        info = {**state.info, "step": state.info["step"] + 1, "render_overflow": overflow}
        return State(data, obs, reward, done, info)

    # --- pieces ---------------------------------------------------------------------------

    def _placed(self, data, key):
        """Objects moved within range at random yaws, footprints clear (module docstring); a
        mounted object (welded to its wall) stays where it is."""
        k = len(self.object_bodies)
        shift_key, yaw_key = jax.random.split(key)
        shifts = jax.random.uniform(shift_key, (k, CANDIDATES, 2), minval=-1.0, maxval=1.0) * self.placement_range
        yaws = jax.random.uniform(yaw_key, (k, CANDIDATES), minval=-jnp.pi, maxval=jnp.pi)
        qpos = data.qpos
        rot0 = quat_to_rotmat(qpos[self.free_qpos[:, None] + np.arange(3, 7)])          # (K, 3, 3)
        centre0 = qpos[self.free_qpos[:, None] + np.arange(3)] + jnp.einsum("kij,kj->ki", rot0, self.body_centres)
        chosen = []
        for i in range(k):
            if self.mounted[i]:
                chosen.append((centre0[i, :2], jnp.zeros((), centre0.dtype)))
                continue
            xy = centre0[i, :2] + shifts[i]                                                    # (C, 2)
            clear = jnp.ones(CANDIDATES, bool)
            for j, (other, _) in enumerate(chosen):
                clear &= jnp.linalg.norm(xy - other, axis=1) > self.radii[i] + self.radii[j] + PLACEMENT_GAP
            found = clear.any()
            pick = jnp.where(found, jnp.argmax(clear), 0)
            chosen.append((jnp.where(found, xy[pick], centre0[i, :2]), jnp.where(found, yaws[i, pick], 0.0)))
        for i, (xy, yaw) in enumerate(chosen):
            if self.mounted[i]:
                continue
            c, s = jnp.cos(yaw), jnp.sin(yaw)
            turn = jnp.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], rot0.dtype)
            rot = turn @ rot0[i]
            centre = jnp.concatenate([xy, centre0[i, 2:]])
            position = centre - rot @ self.body_centres[i]
            start = self.free_qpos[i]
            half = yaw / 2
            quat = quat_multiply(jnp.array([jnp.cos(half), 0.0, 0.0, jnp.sin(half)]), qpos[start + 3:start + 7])
            qpos = qpos.at[start:start + 3].set(position).at[start + 3:start + 7].set(quat)
        return data.replace(qpos=qpos)

    def _reward(self, data, info):
        target = info["target"]
        body = jnp.asarray(self.object_bodies)[target]
        centre = data.xpos[body] + data.xmat[body] @ self.body_centres[target]
        distance = jnp.linalg.norm(centre[:2] - info["goal"])
        up = (data.xmat[body] @ info["start_rotation"].T)[2, 2]
        tilt = jnp.degrees(jnp.arccos(jnp.clip(up, -1.0, 1.0)))
        return -distance, (distance <= script.SUCCESS_DISTANCE) & (tilt <= script.UPRIGHT_DEG)

    def _observe(self, data, goal) -> tuple[dict, jax.Array]:
        k = len(self.object_bodies)
        obs = {"joint_pos": data.qpos[self.joints], "joint_vel": data.qvel[self.dofs],
               "object_poses": jnp.concatenate([data.xpos[self.object_bodies], data.xquat[self.object_bodies]],
                                               axis=1).reshape(k, 7), "goal": goal}
        if not self.cameras:
            return obs, jnp.zeros((), bool)
        from kernels.raster import render_batch
        from phirie_jax.render import pad_gaussians

        rot = quat_to_rotmat(data.xquat[self.attached_bodies].astype(jnp.float32))
        pose = jnp.concatenate([rot, data.xpos[self.attached_bodies][..., None].astype(jnp.float32)], axis=-1)
        bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0]), pose.shape[:-2] + (1, 4))
        pose = jnp.concatenate([pose, bottom], axis=-2)
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
