"""Batched worlds of one ``Environment`` stepped in MuJoCo Warp: ``BatchedEnvironment(..., backend="warp")``.

The same API as the MJX worlds (``batched.BatchedEnvironment``: ``reset``, ``step(steps, ctrl)``,
``set_velocities``, ``body_poses``, ``placements``, ``gaussians``, ``render``), the physics in
``warp_worlds.WarpWorlds``: the environment's own MuJoCo model by default (``collision="parts"``:
every CoACD part, the robot's link meshes and finger capsules; "hull" gives the MJX worlds'
model), so a world is the single environment's MuJoCo C model in float32.

The poses reach the renderer without a host round trip: ``WarpWorlds.poses`` hands the bodies'
positions and quaternions to JAX on the device (DLPack), split over the worlds' devices as the
renderer's mesh splits them (one Warp model per GPU of the mesh; on the CPU one model, the poses
then placed on the mesh), and the placements are computed there (``batched._placements``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from kernels.sharding import BatchMesh, pad_rows
from phirie_jax.construct.physics.warp_batch import warp_devices
from phirie_jax.interact.batched import (
    BatchedEnvironment,
    _body_poses,
    _placements,
    batched_model,
    initial_data,
    inverse_t0_pose0,
)
from phirie_jax.interact.environment import Environment
from phirie_jax.interact.mjx_model import CollisionModel
from phirie_jax.interact.warp_worlds import WarpWorlds


class WarpBatchedEnvironment(BatchedEnvironment):
    """N copies of one ``Environment`` in MuJoCo Warp (module docstring). ``devices``: as the MJX
    worlds' (``kernels.sharding.resolve_devices``); the worlds are padded to a multiple of them
    with copies of world 0. ``contacts`` / ``constraints``: per-world capacities
    (``warp_worlds.capacity`` by default)."""

    def __init__(self, env: Environment, num_worlds: int, collision: CollisionModel | None = None, devices=None,
                 *, backend: str = "warp", contacts: int | None = None, constraints: int | None = None):
        self.env = env
        self.num_worlds = int(num_worlds)
        if self.num_worlds < 1:
            raise ValueError(f"num_worlds {num_worlds} (expected at least 1)")
        self.mesh = BatchMesh.over(devices)
        self.padded_worlds = self.mesh.padded(self.num_worlds)
        self.collision = collision or "parts"
        self.mj_model = batched_model(env, self.collision)
        data = initial_data(self.mj_model, env.robot)
        self.worlds = WarpWorlds(self.mj_model, data, self.padded_worlds, warp_devices(self.mesh.devices),
                                 contacts, constraints, grasp=env.robot is not None)
        self.body_ids = jnp.asarray([o.body_id for o in env.objects], jnp.int32)
        self.inverse_t0_pose0 = inverse_t0_pose0(env, data)
        self._renderer = None

    @property
    def data(self):
        """The worlds' ``mujoco_warp.Data``, one per Warp device (``WarpWorlds.parts``; the pad
        worlds included). Per-world fields on the host: ``worlds.field(name)``."""
        return tuple(p.data for p in self.worlds.parts)

    @data.setter
    def data(self, data) -> None:
        raise AttributeError("the Warp worlds' state is set with set_state(qpos, qvel, ctrl) or reset()")

    def _rows(self, name: str, value, width: int):
        if tuple(value.shape) != (self.num_worlds, width):
            raise ValueError(f"{name} of shape {tuple(value.shape)} (expected ({self.num_worlds}, {width}): "
                             f"worlds × {name}'s size)")
        return pad_rows(value if isinstance(value, jax.Array) else np.asarray(value, np.float32), self.padded_worlds)

    def reset(self) -> None:
        """Every world back to the initial state (``batched.initial_data``)."""
        self.worlds.reset()

    def set_state(self, qpos=None, qvel=None, ctrl=None) -> None:
        """Per-world qpos (N, nq), qvel (N, nv) and/or ctrl (N, nu); poses and contacts follow."""
        m = self.mj_model
        self.worlds.set_state(*(None if v is None else self._rows(name, v, width) for name, v, width in
                                (("qpos", qpos, m.nq), ("qvel", qvel, m.nv), ("ctrl", ctrl, m.nu))))

    def set_velocities(self, qvel) -> None:
        """Per-world generalized velocities (N, nv), e.g. a different throw in each world."""
        self.set_state(qvel=qvel)

    def step(self, steps: int = 1, ctrl=None) -> None:
        """Advance every world by ``steps`` simulator steps, holding ``ctrl`` (N, nu) when given (a
        JAX array on the worlds' GPU is read there)."""
        self.worlds.step(int(steps), None if ctrl is None else self._rows("ctrl", ctrl, self.mj_model.nu))

    def body_poses(self) -> jax.Array:
        """(N, K, 4, 4) T_i(t) of every object's (and robot link's) body in every world."""
        return _body_poses(*self.worlds.poses(self.mesh.rows), self.body_ids)[: self.num_worlds]

    def placements(self) -> jax.Array:
        """(N, K, 4, 4) S_i(t) of every object in every world, computed on the worlds' devices."""
        return _placements(*self.worlds.poses(self.mesh.rows), self.body_ids,
                           self.inverse_t0_pose0)[: self.num_worlds]
