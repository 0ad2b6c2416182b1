"""Many simulated worlds of one scene on MJX, stepped and rendered in single calls.

``BatchedEnvironment(env, num_worlds)`` puts the environment's MuJoCo model on the device
once and holds N copies of its state. ``step`` advances every world in one jitted,
vmapped program; ``render`` places each world's object Gaussians by its own body poses
(``compose_scene``, vmapped over worlds) and rasterizes worlds × cameras in one call
(``phirie_jax.render.render_batch``).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from kernels.gaussians import quat_to_rotmat
from phirie_jax.interact.environment import Environment, compose_scene
from phirie_jax.io.camera import Camera


@functools.partial(jax.jit, static_argnames=("steps",))
def _advance(model, data, steps: int):
    from mujoco import mjx

    def one_world(d):
        return jax.lax.fori_loop(0, steps, lambda _, x: mjx.step(model, x), d)

    return jax.vmap(one_world)(data)


@jax.jit
def _placements(xpos, xquat, body_ids, inverse_t0_pose0):
    """(N, K, 4, 4) S_i(t) for every world from body positions (N, nbody, 3) and quats."""
    rot = quat_to_rotmat(xquat[:, body_ids])                       # (N, K, 3, 3)
    top = jnp.concatenate([rot, xpos[:, body_ids, :, None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0], top.dtype), top.shape[:-2] + (1, 4))
    return jnp.concatenate([top, bottom], axis=-2) @ inverse_t0_pose0


class BatchedEnvironment:
    """N copies of one ``Environment`` on MJX (module docstring)."""

    def __init__(self, env: Environment, num_worlds: int):
        import mujoco
        from mujoco import mjx

        self.env = env
        self.num_worlds = int(num_worlds)
        self.model = mjx.put_model(env.model)
        data = mujoco.MjData(env.model)
        mujoco.mj_forward(env.model, data)
        one = mjx.put_data(env.model, data)
        self.data = jax.tree.map(lambda x: jnp.broadcast_to(x, (self.num_worlds,) + x.shape), one)
        self.body_ids = jnp.asarray([o.body_id for o in env.objects], jnp.int32)
        pose0 = np.stack([o.pose0 for o in env.objects]) if env.objects else np.zeros((0, 4, 4))
        t0 = env.body_poses() if env.objects else np.zeros((0, 4, 4))
        self.inverse_t0_pose0 = jnp.asarray(np.linalg.inv(t0) @ pose0 if env.objects else pose0,
                                            jnp.float32)

    @property
    def timestep(self) -> float:
        return self.env.timestep

    def step(self, steps: int = 1) -> None:
        """Advance every world by ``steps`` simulator steps (one compiled program per count)."""
        self.data = _advance(self.model, self.data, int(steps))

    def set_velocities(self, qvel) -> None:
        """Per-world generalized velocities (N, nv), e.g. a different throw in each world."""
        self.data = self.data.replace(qvel=jnp.asarray(qvel, self.data.qvel.dtype))

    def placements(self) -> jax.Array:
        """(N, K, 4, 4) S_i(t) of every object in every world."""
        return _placements(self.data.xpos.astype(jnp.float32), self.data.xquat.astype(jnp.float32),
                           self.body_ids, self.inverse_t0_pose0)

    def gaussians(self):
        """Every world's scene Gaussians (leaves with a leading (N,) axis)."""
        compose = jax.vmap(compose_scene, in_axes=(None, None, None, 0))
        return compose(self.env.background, self.env.object_gaussians, self.env.body_index, self.placements())

    def render(self, cameras: list[Camera | int], background=(0.0, 0.0, 0.0)):
        """Worlds × cameras in one rasterization call; outputs with leading (N, C) axes."""
        from phirie_jax.render import render_batch

        cams = [self.env.camera(c) for c in cameras]
        worlds = self.gaussians()
        n, c = self.num_worlds, len(cams)
        pairs = jax.tree.map(lambda x: jnp.repeat(x, c, axis=0), worlds)  # world w, camera k → w·C + k
        out = render_batch(pairs, cams * n, background=np.asarray(background, np.float32))
        return jax.tree.map(lambda x: x.reshape((n, c) + x.shape[1:]) if hasattr(x, "shape") and x.ndim
                            and x.shape[0] == n * c else x, out)
