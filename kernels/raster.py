"""Tile-based 3D Gaussian Splatting rasterizer (the method of Kerbl et al. 2023), pure JAX.

Pipeline for one camera (``rasterize``), all static shapes:

1. ``project_gaussians``: EWA projection, 3σ radius, tile rectangle (the bounding box of
   the ellipse the Gaussian's α can reach 1/255 in, within 3σ), SH colour.
2. ``bin_gaussians``: sort visible Gaussians by view depth, expand each into its
   tile intersections in that order (into a buffer of ``capacity`` slots; each slot
   finds its Gaussian by a scatter of marks and a cumulative sum), leave out the tiles
   of the rectangle its α never reaches 1/255 in (``tile_reached``), then stably sort
   the slots by tile id. Each tile's list is thus depth-ordered; its range is where the
   sorted ids change. Non-differentiable bookkeeping.
3. Compositing, front to back per tile with early exit and a recompute-based custom VJP:
   on a GPU the Pallas kernels of ``kernels.composite_pallas`` (one program per tile);
   elsewhere, and as their reference, the pure-JAX work queue of ``kernels.composite``
   (``RasterConfig.compositor`` picks).

Nothing is dropped silently: the output reports the intersections needed
(``num_intersections``) and ``overflow`` when they did not fit the buffer (or, for
the autodiff backward, when the longest tile list exceeded ``tile_capacity``); the
host wrapper (``phirie_jax.render``) retries with a larger power-of-two bucket.

Outputs per pixel: rgb = Σ wᵢ cᵢ + T·background, depth = Σ wᵢ zᵢ (alpha-weighted view
depth, *not* normalized: divide by alpha, ``RasterOutput.depth_normalized``),
alpha = 1 − T, features = Σ wᵢ fᵢ (no background), with wᵢ = αᵢ Tᵢ.
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp

from kernels.composite import NUM_GEOMETRY, TileGrid, TileLists, composite, composite_scan
from kernels.composite_pallas import PallasSettings, composite_pallas
from kernels.gaussians import Gaussians
from kernels.project import ALPHA_MIN, NEAR_PLANE, Projected, project_gaussians
from kernels.pytree import pytree_dataclass, static_field

MAX_INTERSECTIONS = 1 << 30  # beyond this the int32 bookkeeping could overflow: always "overflow"
DEPTH_EPS = 1e-10            # guards depth / alpha where nothing was hit
BASE_COLUMNS = NUM_GEOMETRY + 4  # composite rows before the features: geometry, rgb, depth (when on)
# Tiles in flight (kernels.composite). A CPU wants few: idle slots cost work. A GPU wants
# enough to fill it, but the loop runs about as many steps as the longest tile needs
# whatever the slot count, so extra slots mostly compute masked work. Measured on an H100
# (experiments/bench_render.py): 256 slots for 1.1K tiles (garden 648×420) was 3× faster
# than 1107; 1024 for 8.2K tiles (1080p) matched 512 and 2048 forward, best backward.
CPU_SLOTS = 8
GPU_MIN_SLOTS = 256
GPU_TILES_PER_SLOT = 8


@dataclasses.dataclass(frozen=True)
class RasterConfig:
    """Static rasterizer settings (hashable: each distinct value is one compiled program).

    capacity: tile–Gaussian intersection buffer (a power of two by convention).
    chunk: Gaussians composited per step of a tile's loop.
    slots: tiles in flight in the work queue (None: per backend, see ``CPU_SLOTS``).
    backward: "custom" (recompute-based VJP, early exit) or "autodiff" (fixed-length
        scan, plain reverse mode; needs ``tile_capacity`` ≥ the longest tile list).
    sequential: composite a chunk as the literal 3DGS loop unrolled (one fused kernel)
        instead of the matrix-product formulation; same results, see
        ``resolved_sequential``. The backward is the same either way.
    compositor: "pallas" (``kernels.composite_pallas``), "jax" (``kernels.composite``) or
        "auto": Pallas on a GPU with the custom backward, JAX otherwise.
    depth: composite the depth channel. Off, ``RasterOutput.depth`` is zeros and the
        compositor carries one channel less (training and policy frames need colour only).
    pallas: the Pallas compositor's settings (``interpret=True`` runs it on a CPU).
        ``chunk``, ``slots`` and ``sequential`` above are the JAX compositor's.
    """

    capacity: int = 1 << 18
    tile_size: int = 16
    near: float = NEAR_PLANE
    chunk: int = 32
    slots: int | None = None
    backward: str = "custom"
    tile_capacity: int = 1 << 12
    sequential: bool = False
    compositor: str = "auto"
    pallas: PallasSettings = PallasSettings()
    depth: bool = True

    def resolved_compositor(self) -> str:
        """"pallas" or "jax" (see ``compositor``)."""
        if self.compositor == "auto":
            gpu = jax.default_backend() in ("gpu", "cuda")
            return "pallas" if gpu and self.backward == "custom" else "jax"
        if self.compositor not in ("pallas", "jax"):
            raise ValueError(f"RasterConfig.compositor: {self.compositor!r} "
                             "(expected 'auto', 'pallas' or 'jax')")
        if self.compositor == "pallas" and self.backward != "custom":
            raise ValueError("RasterConfig: the Pallas compositor has only the custom backward")
        return self.compositor

    def resolved_sequential(self) -> bool:
        """Chunk compositing as one fused sequential loop? Off by default: on an H100 it
        was up to 3× faster in isolation but erratic inside the loop (2–7× slower at some
        slot counts) and 5–15× slower to compile; on a CPU no faster."""
        return bool(self.sequential)

    def resolved_slots(self, num_tiles: int) -> int:
        slots = self.slots
        if slots is None:
            if jax.default_backend() == "cpu":
                slots = CPU_SLOTS
            else:
                slots = max(GPU_MIN_SLOTS, num_tiles // GPU_TILES_PER_SLOT)
        return max(1, min(slots, num_tiles))


@pytree_dataclass
class RasterOutput:
    """Images and diagnostics of one render (leading batch dims under ``render_batch``)."""

    rgb: jax.Array                     # (H, W, 3) composited over the background
    depth: jax.Array                   # (H, W) Σ wᵢ zᵢ, alpha-weighted, not normalized
    alpha: jax.Array                   # (H, W) 1 − final transmittance
    features: jax.Array                # (H, W, F) Σ wᵢ fᵢ (F may be 0)
    radii: jax.Array                   # (N,) 3σ screen radius, 0 where culled
    num_visible: jax.Array             # () int32 Gaussians touching at least one tile
    num_intersections: jax.Array       # () int32 tile intersections needed
    max_tile_intersections: jax.Array  # () int32 longest tile list (of what fitted)
    overflow: jax.Array                # () bool: something did not fit; the image is incomplete
    steps: jax.Array                   # () int32 compositing loop iterations (for tuning)
    capacity: int = static_field(default=0)

    @property
    def depth_normalized(self) -> jax.Array:
        """(H, W) expected depth of what was hit: depth / alpha (0 where alpha is 0)."""
        return jnp.where(self.alpha > 0, self.depth / jnp.maximum(self.alpha, DEPTH_EPS), 0.0)


def tile_reached(means2d, conics, opacities, tx, ty, tile_size: int):
    """Whether a Gaussian's α reaches ALPHA_MIN at some pixel centre of tile (tx, ty).

    means2d (M, 2), conics (M, 3) (a, b, c), opacities (M,), tx (M,), ty (M,) int32: one
    (Gaussian, tile) pair per row. α = o exp(−q/2) with q = a dx² + 2b dx dy + c dy² is at least
    ALPHA_MIN where q ≤ 2 ln(o / ALPHA_MIN); the smallest q over the tile's rectangle of pixel
    centres is 0 when the mean is inside it, else on one of its edges, where q is a parabola in
    the free coordinate (its vertex clamped to the edge). Returns (M,) bool (a margin of 1e-3 in
    q keeps every pair that rounding could make the compositor keep)."""
    a, b, c = conics[:, 0], conics[:, 1], conics[:, 2]
    lo_x = (tx * tile_size).astype(means2d.dtype) + 0.5 - means2d[:, 0]
    lo_y = (ty * tile_size).astype(means2d.dtype) + 0.5 - means2d[:, 1]
    hi_x, hi_y = lo_x + (tile_size - 1), lo_y + (tile_size - 1)

    def along_y(dx):   # the smallest q on the edge at offset dx, dy in [lo_y, hi_y]
        dy = jnp.clip(-b * dx / c, lo_y, hi_y)
        return a * dx * dx + 2.0 * b * dx * dy + c * dy * dy

    def along_x(dy):
        dx = jnp.clip(-b * dy / a, lo_x, hi_x)
        return a * dx * dx + 2.0 * b * dx * dy + c * dy * dy

    inside = (lo_x <= 0.0) & (hi_x >= 0.0) & (lo_y <= 0.0) & (hi_y >= 0.0)
    q = jnp.minimum(jnp.minimum(along_y(lo_x), along_y(hi_x)), jnp.minimum(along_x(lo_y), along_x(hi_y)))
    limit = 2.0 * jnp.log(jnp.maximum(opacities, ALPHA_MIN) / ALPHA_MIN)
    return inside | (q <= limit + 1e-3)


def _rect_tiles(rects):
    """rects (N, 4) int32 inclusive tile rectangles → span in x (N,) and tile count (N,) int32
    (0 for an empty rectangle)."""
    x0, y0, x1, y1 = (rects[:, i] for i in range(4))
    span_x = jnp.maximum(x1 - x0 + 1, 0)
    return span_x, span_x * jnp.maximum(y1 - y0 + 1, 0)


def _too_many(counts):
    """Could the int32 sum of counts (N,) wrap? (a float sum tells, for absurd scenes) → () bool."""
    return jnp.sum(counts.astype(jnp.float32)) > MAX_INTERSECTIONS


def intersections_needed(gaussians: Gaussians, K, world_to_camera, *, width: int, height: int,
                         config: RasterConfig = RasterConfig()):
    """The buffer slots (tile intersections) ``rasterize`` needs for this view: the
    ``num_intersections`` it would report, from the projection alone (no binning, no
    compositing). K (3, 3), world_to_camera (4, 4) → () int32."""
    proj = project_gaussians(gaussians, K, world_to_camera, width=width, height=height,
                             tile_size=config.tile_size, near=config.near)
    _, counts = _rect_tiles(proj.rects)
    return jnp.where(_too_many(counts), jnp.iinfo(jnp.int32).max, jnp.sum(counts, dtype=jnp.int32))


def bin_gaussians(proj: Projected, grid: TileGrid, capacity: int):
    """Depth-ordered per-tile lists.  Returns (TileLists, needed intersections () int32).

    Every tile of a Gaussian's rectangle takes a slot; slots past ``capacity`` are not
    stored, and ``needed`` says how many there were. A slot whose tile the Gaussian's α never
    reaches ALPHA_MIN in (``tile_reached``: the rectangle's corners, for an elongated or
    faint Gaussian) is left out of the lists: it sorts after every tile's run.
    """
    n = proj.depths.shape[0]
    x0, y0 = proj.rects[:, 0], proj.rects[:, 1]
    span_x, counts = _rect_tiles(proj.rects)
    depth_key = jnp.where(counts > 0, jax.lax.stop_gradient(proj.depths), jnp.inf)
    _, order = jax.lax.sort_key_val(depth_key, jnp.arange(n, dtype=jnp.int32))  # stable
    counts_sorted = counts[order]
    ends = jnp.cumsum(counts_sorted, dtype=jnp.int32)  # (N,) exclusive end of each run
    too_many = _too_many(counts)
    needed = jnp.where(too_many, jnp.iinfo(jnp.int32).max, ends[-1])

    # Owner of each slot: a 1 at the first slot of every visible Gaussian, whose running
    # sum is the owner's rank in depth order (visible Gaussians sort first: the culled ones'
    # keys are +inf). One scatter and one cumulative sum (a library scan on a GPU).
    starts = ends - counts_sorted
    marks = jnp.zeros(capacity, jnp.int32).at[jnp.where(counts_sorted > 0, starts, capacity)].add(
        1, mode="drop")
    rank = jnp.maximum(jnp.cumsum(marks, dtype=jnp.int32) - 1, 0)
    slot = jnp.arange(capacity, dtype=jnp.int32)
    gid = order[rank]
    local = slot - starts[rank]  # index inside the Gaussian's rectangle
    width = jnp.maximum(span_x[gid], 1)
    tx, ty = x0[gid] + local % width, y0[gid] + local // width
    tile = ty * grid.tiles_x + tx
    nt = grid.num_tiles
    reached = tile_reached(jax.lax.stop_gradient(proj.means2d[gid]), jax.lax.stop_gradient(proj.conics[gid]),
                           jax.lax.stop_gradient(proj.opacities[gid]), tx, ty, grid.tile_size)
    tile = jnp.where((slot < needed) & ~too_many & reached, tile, nt)  # sentinel sorts last
    # Stable: entries of one tile keep the depth order they were expanded in.
    sorted_tile, gaussian_ids = jax.lax.sort((tile, gid), num_keys=1, is_stable=True)
    # Each tile's run: its last entry is where the next entry's tile differs.
    following = jnp.concatenate([sorted_tile[1:], jnp.full((1,), nt, jnp.int32)])
    run_end = jnp.zeros(nt, jnp.int32).at[jnp.where(following != sorted_tile, sorted_tile, nt)].set(
        slot + 1, mode="drop")
    # An empty tile's end is that of the last non-empty tile before it (0 if none).
    run_end = jax.lax.cummax(run_end)
    tile_start = jnp.concatenate([jnp.zeros((1,), jnp.int32), run_end[:-1]])
    tile_count = run_end - tile_start
    return TileLists(gaussian_ids, tile_start, tile_count), needed


def _tiles_to_image(grid: TileGrid, x):
    """x (NT, P, ...) per-tile pixels → (H, W, ...) image."""
    ts, ty, tx = grid.tile_size, grid.tiles_y, grid.tiles_x
    rest = x.shape[2:]
    x = x.reshape((ty, tx, ts, ts) + rest)
    x = jnp.moveaxis(x, 2, 1).reshape((ty * ts, tx * ts) + rest)
    return x[: grid.height, : grid.width]


def rasterize(gaussians: Gaussians, K, world_to_camera, *, width: int, height: int,
              background=None, features=None, config: RasterConfig = RasterConfig(),
              means2d_offset=None) -> RasterOutput:
    """Render N Gaussians into one camera.

    gaussians: N Gaussians; K (3, 3); world_to_camera (4, 4) OpenCV axes; width, height:
    static image size; background (3,) (default black); features (N, F) extra channels
    composited like colour (no background); means2d_offset (N, 2) pixels added to the
    projected means (pass zeros and differentiate: its gradient is dL/d means2d, the
    screen-space gradient 3DGS densification thresholds).
    Differentiable in every Gaussian parameter, in ``features``, ``background`` and
    ``means2d_offset``; jit with ``width``, ``height``, ``config`` static.
    """
    grid = TileGrid(width, height, config.tile_size)
    dtype = gaussians.means.dtype
    n = gaussians.num
    proj = project_gaussians(gaussians, K, world_to_camera, width=width, height=height,
                             tile_size=config.tile_size, near=config.near)
    if means2d_offset is not None:
        proj = proj.replace(means2d=proj.means2d + means2d_offset)
    if features is None:
        features = jnp.zeros((n, 0), dtype)
    background = jnp.zeros(3, dtype) if background is None else jnp.asarray(background, dtype)
    params = composite_params(proj, features, config.depth)  # (N, D) rows of kernels.composite

    lists, needed = bin_gaussians(jax.lax.stop_gradient(proj), grid, config.capacity)
    acc, trans, steps, too_long = composite_rows(grid, config, params, lists)
    rgb, depth, alpha, feats = images_from_tiles(grid, acc, trans, background, config.depth)
    return RasterOutput(
        rgb=rgb, depth=depth, alpha=alpha, features=feats,
        radii=jax.lax.stop_gradient(proj.radii),
        num_visible=jnp.sum(proj.visible, dtype=jnp.int32),
        num_intersections=needed,
        max_tile_intersections=jnp.max(lists.tile_count),
        overflow=(needed > config.capacity) | too_long,
        steps=steps,
        capacity=config.capacity,
    )


def base_columns(depth: bool) -> int:
    """Composite rows' columns before the features: geometry, rgb and, when on, depth."""
    return BASE_COLUMNS if depth else BASE_COLUMNS - 1


def composite_params(proj: Projected, features, depth: bool = True):
    """Rows of ``kernels.composite`` for projected Gaussians: features (N, F) →
    (N, 6 + 3 + 1 + F) [μx, μy, a, b, c, opacity, r, g, b, depth, features...] (no depth
    column when ``depth`` is off)."""
    depths = [proj.depths[:, None]] if depth else []
    return jnp.concatenate([proj.means2d, proj.conics, proj.opacities[:, None], proj.colors, *depths,
                            features.astype(proj.means2d.dtype)], axis=1)


def composite_rows(grid: TileGrid, config: RasterConfig, params, lists: TileLists):
    """Composite parameter rows params (N, D) through depth-sorted tile lists with the
    configured compositor.  Returns acc (NT, P, D − 6), T (NT, P), steps () int32 and
    too_long () bool (a tile list longer than the autodiff scan covers: incomplete)."""
    too_long = jnp.zeros((), bool)
    if config.resolved_compositor() == "pallas":
        acc, trans, steps = composite_pallas(grid, config.pallas, params, lists.gaussian_ids,
                                             lists.tile_start, lists.tile_count)
    elif config.backward == "custom":
        slots = config.resolved_slots(grid.num_tiles)
        acc, trans, steps = composite(grid, slots, config.chunk, config.resolved_sequential(),
                                      params, lists.gaussian_ids, lists.tile_start,
                                      lists.tile_count)
    elif config.backward == "autodiff":
        max_chunks = -(-config.tile_capacity // config.chunk)
        acc, trans = composite_scan(grid, config.chunk, max_chunks, params, lists)
        steps = jnp.asarray(max_chunks, jnp.int32)
        too_long = jnp.max(lists.tile_count) > max_chunks * config.chunk
    else:
        raise ValueError(f"RasterConfig.backward: {config.backward!r} (expected 'custom' or 'autodiff')")
    return acc, trans, steps, too_long


def images_from_tiles(grid: TileGrid, acc, trans, background, depth: bool = True):
    """Per-tile sums acc (NT, P, 4 + F) (3 + F without depth) and transmittance trans (NT, P)
    → rgb (H, W, 3) over background (3,), depth (H, W) (zeros without it), alpha (H, W),
    features (H, W, F)."""
    acc = _tiles_to_image(grid, acc)
    trans = _tiles_to_image(grid, trans)
    rgb = acc[..., :3] + trans[..., None] * background
    if not depth:
        return rgb, jnp.zeros_like(trans), 1.0 - trans, acc[..., 3:]
    return rgb, acc[..., 3], 1.0 - trans, acc[..., 4:]


def render_batch(gaussians: Gaussians, Ks, world_to_cameras, *, width: int, height: int,
                 background=None, features=None, config: RasterConfig = RasterConfig()
                 ) -> RasterOutput:
    """Many cameras (and optionally as many Gaussian sets of equal size) in one call.

    Ks (B, 3, 3), world_to_cameras (B, 4, 4). gaussians: one set (means (N, 3)) shared by
    every camera, or B sets (means (B, N, 3)), the b-th rendered by the b-th camera.
    features (N, F) or (B, N, F) or None; background (3,) or (B, 3) or None.
    Returns a ``RasterOutput`` whose fields have a leading B.
    """
    g_axis = 0 if gaussians.means.ndim == 3 else None
    f_axis = 0 if features is not None and features.ndim == 3 else None
    b_axis = 0 if background is not None and jnp.ndim(background) == 2 else None
    fn = partial(rasterize, width=width, height=height, config=config)
    return jax.vmap(
        lambda g, k, w, bg, f: fn(g, k, w, background=bg, features=f),
        in_axes=(g_axis, 0, 0, b_axis, f_axis),
    )(gaussians, Ks, world_to_cameras, background, features)

