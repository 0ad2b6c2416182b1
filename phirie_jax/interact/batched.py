"""Many simulated worlds of one scene on MJX, stepped and rendered in single calls.

``BatchedEnvironment(env, num_worlds)`` puts the environment's MuJoCo model on the device
once and holds N copies of its state. By default the objects collide through one convex hull
each (``collision="hull"``, ``phirie_jax.interact.mjx_model``: MJX compiles one function per
distinct part pair); ``collision="parts"`` keeps the exported parts, as the single environment. ``step`` advances every world in one jitted,
vmapped program; ``render`` places each world's object Gaussians by its own body poses
(``compose_scene``, vmapped over worlds) and rasterizes worlds × cameras in one call
(``phirie_jax.render.render_batch``).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from kernels.gaussians import quat_to_rotmat
from phirie_jax.interact.environment import Environment, compose_scene, load_spec
from phirie_jax.interact.mjx_model import CollisionModel, hull_collision_spec, multi_part
from phirie_jax.types import Camera


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

    def __init__(self, env: Environment, num_worlds: int, collision: CollisionModel = "hull"):
        import mujoco
        from mujoco import mjx

        self.env = env
        self.num_worlds = int(num_worlds)
        self.collision = collision
        if collision not in ("hull", "parts"):
            raise ValueError(f"collision {collision!r} (expected 'hull' or 'parts')")
        merged = [o.body for o in env.objects if collision == "hull" and multi_part(env.model, o.body_id)]
        if merged:
            self.mj_model = hull_collision_spec(load_spec(env.out_dir, env.with_pusher), env.model, merged).compile()
        else:
            self.mj_model = env.model
        self.model = mjx.put_model(self.mj_model)
        data = mujoco.MjData(self.mj_model)
        mujoco.mj_forward(self.mj_model, data)
        one = mjx.put_data(self.mj_model, data)
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

    def gaussians(self, worlds=None):
        """Scene Gaussians of every world, or of the given world indices (leading (N,) axis)."""
        placements = self.placements()
        if worlds is not None:
            placements = placements[jnp.asarray(worlds)]
        compose = jax.vmap(compose_scene, in_axes=(None, None, None, 0))
        return compose(self.env.background, self.env.object_gaussians, self.env.body_index, placements)

    def render(self, cameras: list[Camera | int], background=(0.0, 0.0, 0.0), max_images: int = 64):
        """Worlds × cameras; outputs with leading (N, C) axes.

        One rasterization call renders up to ``max_images`` images (every camera of
        ``max_images // C`` worlds; the last call is padded to the same size, so one compiled
        program serves every call): N worlds' scenes at once would not fit a GPU's memory.
        """
        from phirie_jax.render import render_batch

        cams = [self.env.camera(c) for c in cameras]
        n, c = self.num_worlds, len(cams)
        per = max(1, min(n, max_images // c))
        chunks = []
        for start in range(0, n, per):
            worlds = np.minimum(np.arange(start, start + per), n - 1)
            pairs = jax.tree.map(lambda x: jnp.repeat(x, c, axis=0), self.gaussians(worlds))  # w·C + k
            out = render_batch(pairs, cams * per, background=np.asarray(background, np.float32))
            keep = min(per, n - start) * c
            chunks.append(jax.tree.map(lambda x: x[:keep] if _batched(x, per * c) else x, out))
        last = chunks[-1]  # a capacity retry may have changed the static fields: take the last's
        out = dataclasses.replace(last, **{f.name: jnp.concatenate([getattr(ch, f.name) for ch in chunks])
                                          for f in dataclasses.fields(last) if _batched(getattr(last, f.name), None)})
        return jax.tree.map(lambda x: x.reshape((n, c) + x.shape[1:]) if _batched(x, n * c) else x, out)


def _batched(x, size: int | None) -> bool:
    """Whether a render output field carries the image axis (of ``size`` when given)."""
    return hasattr(x, "shape") and x.ndim > 0 and (size is None or x.shape[0] == size)
