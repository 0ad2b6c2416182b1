"""Many simulated worlds of one scene on MJX, stepped and rendered in single calls.

``BatchedEnvironment(env, num_worlds)`` puts the environment's MuJoCo model on the device
once and holds N copies of its state. By default the objects collide through one convex hull
each (``collision="hull"``, ``phirie_jax.interact.mjx_model``: MJX compiles one function per
distinct part pair); ``collision="parts"`` keeps the exported parts, as the single environment. ``step`` advances every world in one jitted,
vmapped program; ``render`` draws worlds × cameras with a ``WorldRenderer``.

``WorldRenderer`` renders many worlds of one environment from the same cameras: the
Gaussians that never move (the background) are projected, coloured and binned once per camera
(``kernels.raster_merge.static_view``); per world only the Gaussians attached to bodies — the
environment's ``object_gaussians`` with their ``body_index``, whatever bodies they belong
to — are placed by that world's body placements, projected, binned and merged into the
static tile lists by depth (``rasterize_over_static``), so each world's image is the single
environment's render of the same state (one depth order per pixel).

Several devices (``devices=``, default every device JAX sees): the worlds are spread over a 1-D
mesh (``kernels.sharding.BatchMesh``): their count is padded to a multiple of the devices' (the
pad worlds are copies of world 0 that are stepped and never reported), the state is split along
the worlds axis with a ``NamedSharding``, the model and the background's tile lists are
replicated, and ``step`` and ``render`` are each one program in which every device runs its own
worlds. ``render`` draws ``max_images`` images per device and call.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from kernels.gaussians import Gaussians, Sim3, quat_to_rotmat, transform_bodies
from kernels.raster import RasterConfig, RasterOutput
from kernels.raster_merge import StaticView, rasterize_over_static, static_view
from kernels.sharding import BatchMesh, pad_rows
from phirie_jax.interact.environment import Environment, body_matrix, compose_scene, load_spec
from phirie_jax.interact.mjx_model import CollisionModel, hull_collision_spec, multi_part
from phirie_jax.render import (
    INITIAL_CAPACITY,
    INTERSECTIONS_GUESS,
    camera_arrays,
    grown_capacity,
    next_power_of_two,
    pad_gaussians,
)
from phirie_jax.types import Camera

MAX_IMAGES = 256  # images per rasterization call and device: bounds the merged lists' memory


@functools.partial(jax.jit, static_argnames=("steps", "mesh"))
def _advance(model, data, steps: int, mesh: BatchMesh):
    """Every world ``steps`` steps on; each device steps its own worlds (``BatchMesh.map``)."""
    from mujoco import mjx

    def worlds(model, data):
        def one_world(d):
            return jax.lax.fori_loop(0, steps, lambda _, x: mjx.step(model, x), d)

        return jax.vmap(one_world)(data)

    return mesh.map(worlds, (False, True))(model, data)


@jax.jit
def _placements(xpos, xquat, body_ids, inverse_t0_pose0):
    """(N, K, 4, 4) S_i(t) for every world from body positions (N, nbody, 3) and quats."""
    rot = quat_to_rotmat(xquat[:, body_ids])                       # (N, K, 3, 3)
    top = jnp.concatenate([rot, xpos[:, body_ids, :, None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0], top.dtype), top.shape[:-2] + (1, 4))
    return jnp.concatenate([top, bottom], axis=-2) @ inverse_t0_pose0


class BatchedEnvironment:
    """N copies of one ``Environment`` on MJX (module docstring), spread over ``devices``
    (``kernels.sharding.resolve_devices``: None, every device; a count; or jax devices)."""

    def __init__(self, env: Environment, num_worlds: int, collision: CollisionModel = "hull", devices=None):
        import mujoco
        from mujoco import mjx

        self.env = env
        self.num_worlds = int(num_worlds)
        if self.num_worlds < 1:
            raise ValueError(f"num_worlds {num_worlds} (expected at least 1)")
        self.mesh = BatchMesh.over(devices)
        self.padded_worlds = self.mesh.padded(self.num_worlds)  # the worlds stepped: a multiple of the devices
        self.collision = collision
        if collision not in ("hull", "parts"):
            raise ValueError(f"collision {collision!r} (expected 'hull' or 'parts')")
        merged = [o.body for o in env.objects if collision == "hull" and multi_part(env.model, o.body_id)]
        if merged:
            self.mj_model = hull_collision_spec(_source_spec(env), env.model, merged).compile()
        else:
            self.mj_model = env.model
        self.model = self.mesh.put_replicated(mjx.put_model(self.mj_model))
        data = mujoco.MjData(self.mj_model)
        mujoco.mj_forward(self.mj_model, data)
        one = jax.device_get(mjx.put_data(self.mj_model, data))
        self._data = self.mesh.put_rows(jax.tree.map(
            lambda x: np.broadcast_to(x, (self.padded_worlds,) + np.shape(x)), one))
        self.body_ids = jnp.asarray([o.body_id for o in env.objects], jnp.int32)
        pose0 = np.stack([o.pose0 for o in env.objects]) if env.objects else np.zeros((0, 4, 4))
        # T_i(0) from the model's initial state, as the worlds start (not the environment's
        # current state, which may have been stepped)
        t0 = (body_matrix(data.xpos[[o.body_id for o in env.objects]],
                          data.xquat[[o.body_id for o in env.objects]])
              if env.objects else np.zeros((0, 4, 4)))
        self.inverse_t0_pose0 = jnp.asarray(np.linalg.inv(t0) @ pose0 if env.objects else pose0,
                                            jnp.float32)
        self._renderer: WorldRenderer | None = None

    @property
    def timestep(self) -> float:
        return self.env.timestep

    @property
    def devices(self) -> tuple:
        return self.mesh.devices

    @property
    def data(self):
        """The worlds' state (``mjx.Data``, leading (N,) axis; the pad worlds left out)."""
        if self.padded_worlds == self.num_worlds:
            return self._data
        return jax.tree.map(lambda x: x[: self.num_worlds], self._data)

    @data.setter
    def data(self, data) -> None:
        """Set the state of the N worlds (the pad worlds become copies of world 0)."""
        self._data = self.mesh.put_rows(pad_rows(data, self.padded_worlds))

    def step(self, steps: int = 1) -> None:
        """Advance every world by ``steps`` simulator steps (one compiled program per count)."""
        self._data = _advance(self.model, self._data, int(steps), self.mesh)

    def set_velocities(self, qvel) -> None:
        """Per-world generalized velocities (N, nv), e.g. a different throw in each world."""
        qvel = np.asarray(qvel, self._data.qvel.dtype)
        if qvel.shape != (self.num_worlds, self._data.qvel.shape[1]):
            raise ValueError(f"set_velocities: qvel of shape {qvel.shape} "
                             f"(expected ({self.num_worlds}, {self._data.qvel.shape[1]}): worlds × nv)")
        self._data = self._data.replace(qvel=self.mesh.put_rows(pad_rows(qvel, self.padded_worlds)))

    def placements(self) -> jax.Array:
        """(N, K, 4, 4) S_i(t) of every object in every world."""
        return _placements(self._data.xpos.astype(jnp.float32), self._data.xquat.astype(jnp.float32),
                           self.body_ids, self.inverse_t0_pose0)[: self.num_worlds]

    def gaussians(self, worlds=None):
        """Scene Gaussians of every world, or of the given world indices (leading (N,) axis)."""
        placements = self.placements()
        if worlds is not None:
            placements = placements[jnp.asarray(worlds)]
        compose = jax.vmap(compose_scene, in_axes=(None, None, None, 0))
        return compose(self.env.background, self.env.object_gaussians, self.env.body_index, placements)

    def render(self, cameras: list[Camera | int], background=(0.0, 0.0, 0.0),
               max_images: int = MAX_IMAGES) -> RasterOutput:
        """Worlds × cameras; outputs with leading (N, C) axes (``WorldRenderer.render``)."""
        if self._renderer is None:
            self._renderer = WorldRenderer(self.env, devices=self.mesh.devices)
        return self._renderer.render(self.placements(), cameras, background, max_images)


def _source_spec(env: Environment):
    """The MjSpec the environment's model came from (its robot and pusher included), or the
    scene folder's when it was built from a compiled model."""
    try:
        return env.spec()
    except RuntimeError:
        return load_spec(env.out_dir, env.with_pusher)


@functools.partial(jax.jit, static_argnames=("width", "height", "config"))
def _static_views(background: Gaussians, Ks, world_to_cameras, *, width: int, height: int,
                  config: RasterConfig) -> StaticView:
    """The background binned for each of C cameras: Ks (C, 3, 3), world_to_cameras (C, 4, 4)."""
    return jax.vmap(lambda K, W: static_view(background, K, W, width=width, height=height,
                                             config=config))(Ks, world_to_cameras)


@functools.partial(jax.jit, static_argnames=("width", "height", "config", "moving_capacity", "mesh"))
def _render_worlds(views: StaticView, attached: Gaussians, body, placements, Ks, world_to_cameras,
                   background, *, width: int, height: int, config: RasterConfig,
                   moving_capacity: int, mesh: BatchMesh) -> RasterOutput:
    """Images (W, C) of W worlds: attached Gaussians (Nm) with body (Nm,) int32, placements
    (W, K, 4, 4) canonical → world per body (W a multiple of the mesh's devices, each rendering
    its own worlds), views of C cameras (Ks (C, 3, 3), world_to_cameras (C, 4, 4)), background (3,)."""

    def worlds(views, attached, body, placements, Ks, world_to_cameras, background):
        def one_world(placement):
            moved = transform_bodies(attached, Sim3.from_matrix(placement), body)
            return jax.vmap(lambda view, K, W: rasterize_over_static(
                view, moved, K, W, width=width, height=height, moving_capacity=moving_capacity,
                background=background, config=config))(views, Ks, world_to_cameras)

        return jax.vmap(one_world)(placements)

    return mesh.map(worlds, (False, False, False, True, False, False, False))(
        views, attached, body, placements, Ks, world_to_cameras, background)


class WorldRenderer:
    """Renders many worlds of one ``Environment`` from shared cameras (module docstring).

    The background's tile lists are kept per camera set (the background never moves); the
    capacities of both sets start from a guess and grow, as ``phirie_jax.render.Renderer``'s,
    when a render reports overflow, so nothing is dropped. The worlds of a call are spread over
    ``devices`` (``kernels.sharding.resolve_devices``: None, every device), all else replicated.
    """

    def __init__(self, env: Environment, config: RasterConfig = RasterConfig(), devices=None):
        self.env = env
        self.config = config
        self.mesh = BatchMesh.over(devices)
        attached, body = env.object_gaussians, env.body_index
        if attached.num == 0:  # no body: one transparent Gaussian keeps the shapes non-empty
            attached, body = pad_gaussians(attached, 1), jnp.zeros(1, jnp.int32)
        self.attached, self.body = self.mesh.put_replicated((attached, jnp.asarray(body, jnp.int32)))
        self.moving_capacity = next_power_of_two(max(INITIAL_CAPACITY // 16,
                                                     INTERSECTIONS_GUESS * attached.num))
        self._views: dict[tuple, tuple[StaticView, RasterConfig]] = {}
        self.retries = 0

    def views(self, cameras: list[Camera], dtype=np.float32):
        """Static views of the background for these cameras (cached): (views, config, Ks,
        world_to_cameras, width, height)."""
        arrays = [camera_arrays(c, None, dtype) for c in cameras]
        sizes = {(a[2], a[3]) for a in arrays}
        if len(sizes) != 1:
            raise ValueError(f"WorldRenderer: cameras give different image sizes {sorted(sizes)}")
        (width, height), = sizes
        Ks = np.stack([a[0] for a in arrays])
        w2cs = np.stack([a[1] for a in arrays])
        key = (Ks.tobytes(), w2cs.tobytes(), width, height)
        if key not in self._views:
            background = self.env.background
            config = dataclasses.replace(self.config, capacity=next_power_of_two(max(
                INITIAL_CAPACITY, INTERSECTIONS_GUESS * background.num)))
            while True:
                views = _static_views(background, Ks, w2cs, width=width, height=height,
                                      config=config)
                needed = int(jnp.max(views.needed))
                if needed <= config.capacity:
                    break
                self.retries += 1
                config = grown_capacity(config, needed, "render the batched worlds at a lower "
                                                        "resolution")
            self._views[key] = (self.mesh.put_replicated(views), config)
        views, config = self._views[key]
        Ks, w2cs = self.mesh.put_replicated((Ks, w2cs))
        return views, config, Ks, w2cs, width, height

    def render(self, placements, cameras: list[Camera | int], background=(0.0, 0.0, 0.0),
               max_images: int = MAX_IMAGES) -> RasterOutput:
        """placements (N, K, 4, 4) canonical → world of every body in N worlds; outputs with
        leading (N, C) axes. Each device renders ``max_images // C`` worlds a call (the last
        call padded to the same size, so one compiled program serves every call)."""
        cams = [self.env.camera(c) for c in cameras]
        views, config, Ks, w2cs, width, height = self.views(cams)
        placements = jnp.asarray(placements, jnp.float32)
        if placements.shape[1] == 0:  # no body: the padding Gaussian's placement
            placements = jnp.broadcast_to(jnp.eye(4), (placements.shape[0], 1, 4, 4))
        n, c = placements.shape[0], len(cams)
        per = self.mesh.size * max(1, min(-(-n // self.mesh.size), max_images // c))
        bg = self.mesh.put_replicated(jnp.asarray(background, jnp.float32))
        chunks = []
        for start in range(0, n, per):
            worlds = np.minimum(np.arange(start, start + per), n - 1)
            chunk = self.mesh.put_rows(placements[worlds])
            while True:
                out = _render_worlds(views, self.attached, self.body, chunk, Ks, w2cs,
                                     bg, width=width, height=height, config=config,
                                     moving_capacity=self.moving_capacity, mesh=self.mesh)
                moving_needed = int(jnp.max(out.num_intersections - views.needed[None, :]))
                if moving_needed <= self.moving_capacity:
                    break
                self.retries += 1
                self.moving_capacity = max(2 * self.moving_capacity,
                                           next_power_of_two(moving_needed))
            keep = min(per, n - start)
            chunks.append(jax.tree.map(lambda x, keep=keep: x[:keep], out))
        return jax.tree.map(lambda *x: jnp.concatenate(x), *chunks) if len(chunks) > 1 else chunks[0]
