"""Many simulated worlds of one scene on MJX, stepped and rendered in single calls.

``BatchedEnvironment(env, num_worlds)`` puts the environment's MuJoCo model on the device
once and holds N copies of its state. By default the objects collide through one convex hull
each (``collision="hull"``, ``phirie_jax.interact.mjx_model``: MJX compiles one function per
distinct part pair); ``collision="parts"`` keeps the exported parts, as the single environment. ``step`` advances every world in one jitted,
vmapped program; ``render`` draws worlds × cameras with a ``WorldRenderer``. The worlds start
from the environment's reset state (its robot at home).

``backend="warp"`` (``WarpBatchedEnvironment``) steps the same worlds in MuJoCo Warp instead,
with the same API, the physics in ``warp_worlds.WarpWorlds``: the environment's own MuJoCo model
by default (``collision="parts"``: every CoACD part, the robot's link meshes and finger capsules;
"hull" gives the MJX worlds' model), so a world is the single environment's MuJoCo C model in
float32. Its poses reach the renderer without a host round trip: ``WarpWorlds.poses`` hands the
bodies' positions and quaternions to JAX on the device (DLPack), split over the worlds' devices
as the renderer's mesh splits them (one Warp model per GPU of the mesh; on the CPU one model, the
poses then placed on the mesh), and the placements are computed there (``_placements``).

``WorldRenderer`` renders many worlds of one environment from the same cameras: the
Gaussians that never move (the background) are projected, coloured and binned once per camera
(``kernels.raster_merge.static_view``); per world only the Gaussians attached to bodies — the
environment's ``object_gaussians`` with their ``body_index``, whatever bodies they belong
to — are placed by that world's body placements, projected, binned and merged into the
static tile lists by depth, so each world's image is the single environment's render of the
same state (one depth order per pixel). Only the tiles the moving Gaussians reach are merged
and composited (``rasterize_changed_tiles``); every other tile is the background's own image,
composited once per camera.

Several devices (``devices=``, default every device JAX sees): the worlds are spread over a 1-D
mesh (``kernels.sharding.BatchMesh``): their count is padded to a multiple of the devices' (the
pad worlds are copies of world 0 that are stepped and never reported), the state is split along
the worlds axis with a ``NamedSharding``, the model and the background's tile lists are
replicated, and ``step`` and ``render`` are each one program in which every device runs its own
worlds. ``render`` draws each device's worlds ``max_images`` images at a time, in one program.

Reproducibility: one compiled ``step`` gives the same worlds bit for bit every time it runs from
the same state. Another compilation need not: on a GPU, XLA's autotuner keeps whichever kernel
it timed fastest for a fusion (``--xla_gpu_autotune_level=0`` keeps its default one; the step
then takes 30 % longer on an H100), and the program for another number of devices fuses the
solver's loop differently, so the thrown objects' worlds agree across compilations and device
counts to rounding, which contacts grow (``docs/scaling.md``). A persistent compilation cache
(``phirie_jax.compile_cache``, on in the command line) gives later processes the same program.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from kernels.composite import TileGrid
from kernels.composite_pallas import PallasSettings
from kernels.gaussians import Gaussians, Sim3, quat_to_rotmat, transform_bodies
from kernels.raster import RasterConfig, RasterOutput
from kernels.raster_merge import (
    StaticView,
    TileUse,
    changed_tile_use,
    rasterize_changed_tiles,
    rasterize_over_static,
    static_view,
)
from kernels.sharding import BatchMesh, map_rows, pad_rows
from phirie_jax.construct.physics.warp_batch import warp_devices
from phirie_jax.interact.environment import Environment, compose_scene, load_spec
from phirie_jax.interact.mjx_model import CollisionModel, hull_collision_spec, multi_part
from phirie_jax.interact.warp_worlds import WarpWorlds
from phirie_jax.render import (
    INITIAL_CAPACITY,
    INTERSECTIONS_GUESS,
    camera_arrays,
    grown_capacity,
    next_power_of_two,
    pad_gaussians,
    quarter_octave,
    room_for,
)
from phirie_jax.rotations import pose_matrix
from phirie_jax.types import Camera

MAX_IMAGES = 256  # images rasterized at once per device: bounds the merged lists' memory
# The worlds' compositor reads each chunk's list entries and rows ahead (PallasSettings.prefetch).
# Measured when the changed tiles' rows lay one after another (a strip of rows built per image),
# on one H100, the demo scene's 1,024 worlds × 4 cameras at 640×480: 6,322 frames/s against 5,998
# without, in one process (experiments/results/bench_env_640x480_h100_prefetch.json); on that
# scene only, and not again since the compositor reads the rows where they lie (composite_two_sets).
# Chunks of 16 entries: with the running products (80 registers a thread at 8, 115 at 16), 8,377 and 8,380
# frames/s against 8,220 and 8,241 at 8, alternated in one process; 5,368 at 16 without reading
# ahead (experiments/results/bench_env_640x480_h100_products.json); measured on the demo scene only.
WORLD_RASTER = RasterConfig(pallas=PallasSettings(chunk=16, prefetch=True))
PIXEL_TYPES = {"uint8": jnp.uint8, "bfloat16": jnp.bfloat16, "float32": jnp.float32}


def as_pixels(rgb: jax.Array, pixels: str) -> jax.Array:
    """rgb (..., H, W, 3) in [0, 1] as a policy takes it (``PIXEL_TYPES``): uint8 0–255 (clipped,
    rounded to nearest), bfloat16 or float32 (as rendered)."""
    if pixels not in PIXEL_TYPES:
        raise ValueError(f"pixels: {pixels!r} (expected one of {', '.join(PIXEL_TYPES)})")
    if pixels == "uint8":
        return jnp.round(jnp.clip(rgb, 0.0, 1.0) * 255.0).astype(jnp.uint8)
    return rgb.astype(PIXEL_TYPES[pixels])


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
def _body_poses(xpos, xquat, body_ids):
    """(N, K, 4, 4) T_i(t) of bodies ``body_ids`` (K,) from positions (N, nbody, 3) and wxyz quats."""
    rot = quat_to_rotmat(xquat[:, body_ids])                       # (N, K, 3, 3)
    top = jnp.concatenate([rot, xpos[:, body_ids, :, None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0], top.dtype), top.shape[:-2] + (1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


@jax.jit
def _placements(xpos, xquat, body_ids, inverse_t0_pose0):
    """(N, K, 4, 4) S_i(t) for every world from body positions (N, nbody, 3) and quats."""
    return _body_poses(xpos, xquat, body_ids) @ inverse_t0_pose0


def initial_data(model, robot=None):
    """The state batched worlds start from (``mujoco.MjData``): the model's reset state, the robot
    (``robot.setup.Robot``) at home with its servos holding there, forward done (``Environment.reset``)."""
    import mujoco

    data = mujoco.MjData(model)
    if robot is not None:
        robot.set_home(model, data)
    mujoco.mj_forward(model, data)
    return data


def batched_model(env: Environment, collision: CollisionModel):
    """The ``mujoco.MjModel`` the worlds run: the environment's own (``"parts"``), or with each
    multi-part object colliding through one convex hull (``"hull"``, ``mjx_model``)."""
    if collision not in ("hull", "parts"):
        raise ValueError(f"collision {collision!r} (expected 'hull' or 'parts')")
    merged = [o.body for o in env.objects if collision == "hull" and multi_part(env.model, o.body_id)]
    if merged:
        return hull_collision_spec(_source_spec(env), env.model, merged).compile()
    return env.model


def inverse_t0_pose0(env: Environment, data) -> jax.Array:
    """(K, 4, 4) T_i(0)⁻¹ S_i(0) of the environment's bodies, T_i(0) from ``data``: the state the
    worlds start from (not the environment's current state, which may have been stepped)."""
    if not env.objects:
        return jnp.zeros((0, 4, 4), jnp.float32)
    ids = [o.body_id for o in env.objects]
    pose0 = np.stack([o.pose0 for o in env.objects])
    return jnp.asarray(np.linalg.inv(pose_matrix(data.xpos[ids], data.xquat[ids])) @ pose0, jnp.float32)


class BatchedEnvironment:
    """N copies of one ``Environment`` on MJX (module docstring), spread over ``devices``
    (``kernels.sharding.resolve_devices``: None, every device; a count; or jax devices).

    ``backend="warp"`` gives the same API on MuJoCo Warp (``WarpBatchedEnvironment``:
    the exact model, ``collision`` "parts" by default); "mjx" (default) is the pure-JAX backend,
    ``collision`` "hull" by default."""

    def __new__(cls, *args, backend: str = "mjx", **kwargs):
        if backend not in ("mjx", "warp"):
            raise ValueError(f"backend {backend!r} (expected 'mjx' or 'warp')")
        if backend == "warp" and cls is BatchedEnvironment:
            return super().__new__(WarpBatchedEnvironment)
        return super().__new__(cls)

    def __init__(self, env: Environment, num_worlds: int, collision: CollisionModel | None = None, devices=None,
                 *, backend: str = "mjx"):
        from mujoco import mjx

        self._set_worlds(env, num_worlds, devices)
        self.collision = collision or "hull"
        self.mj_model = batched_model(env, self.collision)
        self.model = self.mesh.put_replicated(mjx.put_model(self.mj_model))
        data = initial_data(self.mj_model, env.robot)
        one = jax.device_get(mjx.put_data(self.mj_model, data))
        self._data0 = self.mesh.put_rows(jax.tree.map(
            lambda x: np.broadcast_to(x, (self.padded_worlds,) + np.shape(x)), one))
        self._data = self._data0
        self.body_ids = jnp.asarray([o.body_id for o in env.objects], jnp.int32)
        self.inverse_t0_pose0 = inverse_t0_pose0(env, data)
        self._renderer: WorldRenderer | None = None

    def _set_worlds(self, env: Environment, num_worlds: int, devices) -> None:
        """The environment, the worlds' count and the mesh of devices they are spread over."""
        self.env = env
        self.num_worlds = int(num_worlds)
        if self.num_worlds < 1:
            raise ValueError(f"num_worlds {num_worlds} (expected at least 1)")
        self.mesh = BatchMesh.over(devices)
        self.padded_worlds = self.mesh.padded(self.num_worlds)  # the worlds stepped: a multiple of the devices

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

    def reset(self) -> None:
        """Every world back to the initial state (``initial_data``)."""
        self._data = self._data0

    def step(self, steps: int = 1, ctrl=None) -> None:
        """Advance every world by ``steps`` simulator steps (one compiled program per count),
        holding ``ctrl`` (N, nu), the actuators' controls of each world, when given."""
        if ctrl is not None:
            nu = self._data.ctrl.shape[1]
            if tuple(ctrl.shape) != (self.num_worlds, nu):
                raise ValueError(f"step: ctrl of shape {tuple(ctrl.shape)} (expected ({self.num_worlds}, {nu}): "
                                 "worlds × actuators)")
            ctrl = pad_rows(jnp.asarray(ctrl, self._data.ctrl.dtype), self.padded_worlds)
            self._data = self._data.replace(ctrl=self.mesh.put_rows(ctrl))
        # put back on the rows' sharding: XLA reports an empty row block (N, 0, ...) as replicated,
        # and the next call would compile the program again for it
        self._data = self.mesh.put_rows(_advance(self.model, self._data, int(steps), self.mesh))

    def set_velocities(self, qvel) -> None:
        """Per-world generalized velocities (N, nv), e.g. a different throw in each world."""
        qvel = np.asarray(qvel, self._data.qvel.dtype)
        if qvel.shape != (self.num_worlds, self._data.qvel.shape[1]):
            raise ValueError(f"set_velocities: qvel of shape {qvel.shape} "
                             f"(expected ({self.num_worlds}, {self._data.qvel.shape[1]}): worlds × nv)")
        self._data = self._data.replace(qvel=self.mesh.put_rows(pad_rows(qvel, self.padded_worlds)))

    def body_poses(self) -> jax.Array:
        """(N, K, 4, 4) T_i(t): world pose of every object's (and robot link's) body in every world."""
        return _body_poses(self._data.xpos.astype(jnp.float32), self._data.xquat.astype(jnp.float32),
                           self.body_ids)[: self.num_worlds]

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
               max_images: int = MAX_IMAGES, pixels: str | None = None) -> RasterOutput | jax.Array:
        """Worlds × cameras; outputs with leading (N, C) axes, or with ``pixels`` the colour
        alone in that type (``WorldRenderer.render``)."""
        if self._renderer is None:
            self._renderer = WorldRenderer(self.env, devices=self.mesh.devices)
        return self._renderer.render(self.placements(), cameras, background, max_images, pixels)


class WarpBatchedEnvironment(BatchedEnvironment):
    """N copies of one ``Environment`` in MuJoCo Warp (module docstring). ``devices``: as the MJX
    worlds' (``kernels.sharding.resolve_devices``); the worlds are padded to a multiple of them
    with copies of world 0. ``contacts`` / ``constraints``: per-world capacities
    (``warp_worlds.capacity`` by default)."""

    def __init__(self, env: Environment, num_worlds: int, collision: CollisionModel | None = None, devices=None,
                 *, backend: str = "warp", contacts: int | None = None, constraints: int | None = None):
        self._set_worlds(env, num_worlds, devices)
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


@dataclasses.dataclass(frozen=True)
class WorldCapacities:
    """Slots of one image's lists (``rasterize_changed_tiles``), shared by every world and camera."""

    moving: int    # tile intersections of the moving Gaussians
    tiles: int     # tiles they reach
    entries: int   # background entries in those tiles
    longest: int | None = None  # bounds the background's longest tile list (2^b − 1 for its bit length b): the merge's bisection

    def grown(self, use: TileUse, num_tiles: int) -> WorldCapacities:
        """Room for the largest use (``TileUse`` of every image); unchanged where it fitted. What
        grows to ``room_for`` its use with a quarter to spare, as objects move between renders
        (the changed tiles at most all of the image's): the
        rule by which ``WorldRenderer`` sizes the lists before its first render, so that growing
        to fit and counting ahead agree."""
        moving, tiles, entries = (max(1, int(jnp.max(x))) for x in (use.moving, use.tiles, use.static_entries))
        return WorldCapacities(
            self.moving if moving <= self.moving else room_for(moving, spare=4),
            self.tiles if tiles <= self.tiles else min(num_tiles, room_for(tiles, spare=4)),
            self.entries if entries <= self.entries else room_for(entries, spare=4),
            self.longest)


@functools.partial(jax.jit, static_argnames=("width", "height", "config", "capacities", "mesh", "pixels",
                                             "whole_images", "worlds_per_step"))
def _render_worlds(views: StaticView, attached: Gaussians, body, placements, Ks, world_to_cameras,
                   background, *, width: int, height: int, config: RasterConfig,
                   capacities: WorldCapacities, mesh: BatchMesh, worlds_per_step: int,
                   pixels: str | None = None, whole_images: bool = False
                   ) -> tuple[RasterOutput | jax.Array, TileUse]:
    """Images (W, C) of W worlds: attached Gaussians (Nm) with body (Nm,) int32, placements
    (W, K, 4, 4) canonical → world per body, views of C cameras (Ks (C, 3, 3), world_to_cameras
    (C, 4, 4)), background (3,). The worlds are spread over the mesh's devices, each rendering its
    own ``worlds_per_step`` at a time in one loop (``kernels.sharding.map_rows``).
    A ``RasterOutput``, or with ``pixels`` (``as_pixels``) only the colour in that type,
    (W, C, H, W, 3), nothing else kept in device memory; and each image's ``TileUse`` (W, C).
    ``whole_images``: every tile merged and composited (``rasterize_over_static``; the use then
    counts only the moving intersections)."""

    def one_image(view, moved, K, W, background):
        if not whole_images:
            return rasterize_changed_tiles(
                view, moved, K, W, width=width, height=height, moving_capacity=capacities.moving,
                tile_capacity=capacities.tiles, entry_capacity=capacities.entries,
                longest_static_run=capacities.longest, background=background, config=config)
        out = rasterize_over_static(view, moved, K, W, width=width, height=height,
                                    moving_capacity=capacities.moving, background=background, config=config)
        zero = jnp.zeros((), jnp.int32)
        return out, TileUse(out.num_intersections - view.needed, zero, zero)

    def one_world(shared, placement):
        views, attached, body, Ks, world_to_cameras, background = shared
        moved = transform_bodies(attached, Sim3.from_matrix(placement), body)
        out, use = jax.vmap(lambda view, K, W: one_image(view, moved, K, W, background))(
            views, Ks, world_to_cameras)
        return (out if pixels is None else as_pixels(out.rgb, pixels)), use

    return map_rows(one_world, (views, attached, body, Ks, world_to_cameras, background), placements,
                    worlds_per_step, mesh)


@functools.partial(jax.jit, static_argnames=("width", "height", "config", "moving_capacity", "mesh",
                                             "worlds_per_step"))
def _tile_use(views: StaticView, attached: Gaussians, body, placements, Ks, world_to_cameras, *,
              width: int, height: int, config: RasterConfig, moving_capacity: int, mesh: BatchMesh,
              worlds_per_step: int) -> TileUse:
    """``_render_worlds``' ``TileUse`` (W, C) without rendering (``changed_tile_use``): sizes the
    first render's capacities."""

    def one_world(shared, placement):
        views, attached, body, Ks, world_to_cameras = shared
        moved = transform_bodies(attached, Sim3.from_matrix(placement), body)
        return jax.vmap(lambda view, K, W: changed_tile_use(
            view, moved, K, W, width=width, height=height, moving_capacity=moving_capacity,
            config=config))(views, Ks, world_to_cameras)

    return map_rows(one_world, (views, attached, body, Ks, world_to_cameras), placements, worlds_per_step, mesh)


class WorldRenderer:
    """Renders many worlds of one ``Environment`` from shared cameras (module docstring).

    The background's tile lists and image are kept per camera set (the background never
    moves). The moving lists' capacity starts from a guess, the changed tiles' are counted
    before the first render; all grow, as ``phirie_jax.render.Renderer``'s, when a render
    reports overflow, so nothing is dropped. The worlds of a call are spread over ``devices``
    (``kernels.sharding.resolve_devices``: None, every device), all else replicated.
    ``whole_images``: merge and composite every tile of every image (``rasterize_over_static``),
    the reference the changed-tile render is measured against.
    """

    def __init__(self, env: Environment, config: RasterConfig = WORLD_RASTER, devices=None,
                 whole_images: bool = False):
        self.env = env
        self.config = config
        self.whole_images = whole_images
        self.mesh = BatchMesh.over(devices)
        attached, body = env.object_gaussians, env.body_index
        if attached.num == 0:  # no body: one transparent Gaussian keeps the shapes non-empty
            attached, body = pad_gaussians(attached, 1), jnp.zeros(1, jnp.int32)
        self.attached, self.body = self.mesh.put_replicated((attached, jnp.asarray(body, jnp.int32)))
        self.capacities = WorldCapacities(
            moving=next_power_of_two(max(INITIAL_CAPACITY // 16, INTERSECTIONS_GUESS * attached.num)),
            tiles=0, entries=0)  # 0: every capacity counted before the first render
        self._views: dict[tuple, tuple[StaticView, RasterConfig, int]] = {}
        self.retries = 0

    def views(self, cameras: list[Camera], dtype=np.float32, depth: bool = True):
        """Static views of the background for these cameras (cached): (views, config, Ks,
        world_to_cameras, width, height, a bound on the longest tile list of any of them).
        ``depth`` off: colour-only views (one channel less to composite; what
        ``render(..., pixels=...)`` uses)."""
        arrays = [camera_arrays(c, None, dtype) for c in cameras]
        sizes = {(a[2], a[3]) for a in arrays}
        if len(sizes) != 1:
            raise ValueError(f"WorldRenderer: cameras give different image sizes {sorted(sizes)}")
        (width, height), = sizes
        Ks = np.stack([a[0] for a in arrays])
        w2cs = np.stack([a[1] for a in arrays])
        key = (Ks.tobytes(), w2cs.tobytes(), width, height, depth)
        if key not in self._views:
            background = self.env.background
            config = dataclasses.replace(self.config, depth=depth, capacity=next_power_of_two(max(
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
            if quarter_octave(needed) < config.capacity:
                # The background never moves: its lists need only the slots its busiest camera
                # fills, and every world's merge and composite walks all of them.
                config = dataclasses.replace(config, capacity=quarter_octave(needed))
                views = _static_views(background, Ks, w2cs, width=width, height=height, config=config)
            # the bisection needs the longest list's bit length: one program per bit length
            longest = (1 << int(jnp.max(views.lists.tile_count)).bit_length()) - 1
            self._views[key] = (self.mesh.put_replicated(views), config, longest)
        views, config, longest = self._views[key]
        Ks, w2cs = self.mesh.put_replicated((Ks, w2cs))
        return views, config, Ks, w2cs, width, height, longest

    def _count_capacities(self, views: StaticView, placements, Ks, w2cs, width: int, height: int,
                          config: RasterConfig, num_tiles: int, worlds_per_step: int):
        """Size every list by the most any world of ``placements`` uses (``_tile_use``), with a
        quarter to spare, as objects move: before the first render, so that it compiles once."""
        while True:
            use = _tile_use(views, self.attached, self.body, placements, Ks, w2cs, width=width, height=height,
                            config=config, moving_capacity=self.capacities.moving, mesh=self.mesh,
                            worlds_per_step=worlds_per_step)
            moving = int(jnp.max(use.moving))
            if moving <= self.capacities.moving:
                break
            # the tiles were counted from cut lists: again, with room for every intersection
            self.capacities = dataclasses.replace(self.capacities, moving=next_power_of_two(moving))
        counted = WorldCapacities(moving=0, tiles=0, entries=0, longest=self.capacities.longest).grown(use, num_tiles)
        # the whole-image render has no changed-tile lists: a placeholder slot each
        self.capacities = dataclasses.replace(counted, tiles=1, entries=1) if self.whole_images else counted

    def render(self, placements, cameras: list[Camera | int], background=(0.0, 0.0, 0.0),
               max_images: int = MAX_IMAGES, pixels: str | None = None) -> RasterOutput | jax.Array:
        """placements (N, K, 4, 4) canonical → world of every body in N worlds; outputs with
        leading (N, C) axes. One program renders them all: each device loops over its own worlds,
        ``max_images // C`` at a time (one compiled program per world count; the outputs need
        no concatenation).

        ``pixels`` ("uint8", "bfloat16" or "float32"): only the colour, (N, C, H, W, 3) in that
        type, made inside the rendering program and left on the device(s) (a policy's input);
        None: the whole ``RasterOutput``."""
        if pixels is not None and pixels not in PIXEL_TYPES:
            raise ValueError(f"pixels: {pixels!r} (expected one of {', '.join(PIXEL_TYPES)}, or None)")
        cams = [self.env.camera(c) for c in cameras]
        views, config, Ks, w2cs, width, height, longest = self.views(cams, depth=pixels is None)
        self.capacities = dataclasses.replace(self.capacities, longest=longest)
        placements = jnp.asarray(placements, jnp.float32)
        if placements.shape[1] == 0:  # no body: the padding Gaussian's placement
            placements = jnp.broadcast_to(jnp.eye(4), (placements.shape[0], 1, 4, 4))
        num_tiles = TileGrid(width, height, config.tile_size).num_tiles
        per_step = max(1, max_images // len(cams))
        n = placements.shape[0]
        placements = self.mesh.put_rows(pad_rows(placements, self.mesh.padded(n)))
        if not self.capacities.tiles:
            self._count_capacities(views, placements, Ks, w2cs, width, height, config, num_tiles, per_step)
        bg = self.mesh.put_replicated(jnp.asarray(background, jnp.float32))
        while True:
            out, use = _render_worlds(views, self.attached, self.body, placements, Ks, w2cs, bg, width=width,
                                      height=height, config=config, capacities=self.capacities, mesh=self.mesh,
                                      worlds_per_step=per_step, pixels=pixels, whole_images=self.whole_images)
            grown = self.capacities.grown(use, num_tiles)
            if grown == self.capacities:
                break
            self.retries += 1
            self.capacities = grown
        return jax.tree.map(lambda x: x[:n], out)
