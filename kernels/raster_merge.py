"""Rendering a scene whose Gaussians are mostly static: bin the static set once per camera,
merge the moving set into its tile lists per render.

For many simulated worlds of one scene seen by the same cameras, most Gaussians (the
background) are identical in every world; only the Gaussians attached to bodies move. So,
per camera, ``static_view`` projects the static Gaussians, evaluates their SH colour and
bins them into depth-sorted tile lists once; per world, ``rasterize_over_static`` projects
and bins only the moving Gaussians and merges their lists into the static ones by depth
(per tile, a merge of two sorted lists by rank: a binary search of each moving entry in its
tile's static run, and for each static entry the moving entries ranked before it, a running
maximum over the last entry of each rank), then composites the merged lists with the usual
compositor. The result is the image ``kernels.raster.rasterize``
gives for the concatenation [static, moving]: one depth order per pixel, ties broken as its
stable sort breaks them (static first, then by index).

``rasterize_changed_tiles`` gives the same image with less work: a tile that no moving
Gaussian reaches looks as the static set alone makes it, which ``static_view`` composites
once (``StaticView.acc``, ``StaticView.trans``). Per render only the changed tiles — those
in the moving set's lists — have their static lists gathered and merged with the moving
entries into a compact block of lists, then composited; their pixels then replace the static
ones. The Pallas compositor (a GPU's) composites each list over its own image tile's pixels,
reading each entry's row from the static rows or the moving ones where they lie
(``kernels.composite_pallas.composite_two_sets``). The JAX compositor composites a block of
tiles as wide as the image, each entry's row gathered and its centre moved to its tile's place
in the block (each tile moves up and left, so its coordinates stay in the image's range).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from kernels.composite import TileGrid, TileLists
from kernels.composite_pallas import composite_two_sets
from kernels.gaussians import Gaussians
from kernels.project import project_gaussians
from kernels.pytree import pytree_dataclass
from kernels.raster import (
    RasterConfig,
    RasterOutput,
    base_columns,
    bin_gaussians,
    composite_params,
    composite_rows,
    images_from_tiles,
)


@pytree_dataclass
class StaticView:
    """The static Gaussians as one camera sees them, projected, coloured and binned."""

    params: jax.Array       # (Ns, D) rows of kernels.composite
    lists: TileLists        # their tile lists, sorted by (tile, depth); capacity Cs
    depths: jax.Array       # (Cs,) view depth of each sorted entry, +inf past the lists
    needed: jax.Array       # () int32 tile intersections needed (> Cs: lists incomplete)
    radii: jax.Array        # (Ns,) 3σ screen radius, 0 where culled
    num_visible: jax.Array  # () int32
    acc: jax.Array          # (NT, P, Dc) the static set alone composited per tile pixel (Dc = D − 6)
    trans: jax.Array        # (NT, P) its transmittance
    too_long: jax.Array     # () bool a tile list longer than the autodiff scan covers (acc incomplete)


def static_view(gaussians: Gaussians, K, world_to_camera, *, width: int, height: int,
                features=None, config: RasterConfig = RasterConfig()) -> StaticView:
    """Project, colour and bin Ns static Gaussians for one camera (``config.capacity`` slots).

    K (3, 3); world_to_camera (4, 4); features (Ns, F) or None.
    """
    grid = TileGrid(width, height, config.tile_size)
    proj = jax.lax.stop_gradient(project_gaussians(
        gaussians, K, world_to_camera, width=width, height=height, tile_size=config.tile_size,
        near=config.near))
    if features is None:
        features = jnp.zeros((gaussians.num, 0), proj.means2d.dtype)
    lists, needed = bin_gaussians(proj, grid, config.capacity)
    slot = jnp.arange(config.capacity, dtype=jnp.int32)
    depths = jnp.where(slot < needed, proj.depths[lists.gaussian_ids], jnp.inf)
    params = composite_params(proj, features, config.depth)
    acc, trans, _, too_long = composite_rows(grid, config, params, lists)
    return StaticView(params, lists, depths, needed, proj.radii, jnp.sum(proj.visible, dtype=jnp.int32),
                      acc, trans, too_long)


def _run_of(starts, size: int):
    """(size,) int32: for each position in [0, size) the last run whose start is at or before it
    (starts (R,) int32, non-decreasing; 0 before the first), as ``searchsorted(starts, p,
    "right") - 1``: one scatter and one cumulative sum instead of log R passes."""
    marks = jnp.zeros(size, jnp.int32).at[starts].add(1, mode="drop")
    return jnp.maximum(jnp.cumsum(marks, dtype=jnp.int32) - 1, 0)


def merge_tile_lists(grid: TileGrid, static: TileLists, static_depths, moving: TileLists, moving_depths,
                     offset: int, longest_static_run: int | None = None) -> TileLists:
    """Merge two (tile, depth)-sorted lists into one; static first where depths are equal.

    static: lists of capacity Cs with static_depths (Cs,) sorted entry depths; moving: lists of
    capacity Cm with moving_depths (Cm,) (the entries in its tiles' runs come first); ``offset``
    is added to the moving Gaussian ids (their rows follow the static rows);
    ``longest_static_run``, when given, bounds every static tile's entry count (the bisection
    then takes its bit length in steps, not Cs's). Returns lists of capacity Cs + Cm.
    """
    cs = static.gaussian_ids.shape[0]
    cm = moving.gaussian_ids.shape[0]
    entry = jnp.arange(cm, dtype=jnp.int32)
    # the entries in a tile's run (binning leaves out the tiles a Gaussian's α never reaches)
    valid = entry < jnp.minimum(moving.tile_start[-1] + moving.tile_count[-1], cm)
    # Each moving entry's tile: the sorted entries' tile runs start at moving.tile_start.
    tile = jnp.minimum(_run_of(moving.tile_start, cm), grid.num_tiles - 1)
    # Rank among the static entries: everything before its tile's run plus the run's
    # entries with depth ≤ its own (lower bound of "depth > d" by bisection).
    lo = static.tile_start[tile]
    hi = lo + static.tile_count[tile]

    def bisect(_, bounds_):
        lo_, hi_ = bounds_
        mid = (lo_ + hi_) // 2
        right = (mid < hi_) & (static_depths[jnp.minimum(mid, cs - 1)] <= moving_depths)
        return jnp.where(right, mid + 1, lo_), jnp.where(right, hi_, mid)

    steps = max(1, int(cs if longest_static_run is None else min(cs, longest_static_run)).bit_length())
    # bounded, its steps unrolled into one kernel (on a GPU a loop launches one kernel a step)
    rank, _ = jax.lax.fori_loop(0, steps, bisect, (lo, hi), unroll=longest_static_run is not None)
    rank = jnp.where(valid, rank, cs)
    # A static entry moves back by the number of moving entries ranked at or before it. The
    # ranks never decrease along the entries (both lists are in tile order, then depth order;
    # the entries outside the runs come last, ranked Cs), so for static entry j that number is
    # 1 + the index of the last entry ranked ≤ j: each rank's last entry writes it at its rank
    # (one write per rank, no atomic additions) and a running maximum carries it forward.
    last_of_rank = valid & (rank != jnp.append(rank[1:], cs + 1))
    ends = jnp.zeros(cs, jnp.int32).at[jnp.where(last_of_rank, rank, cs)].set(entry + 1, mode="drop")
    static_pos = jnp.arange(cs, dtype=jnp.int32) + jax.lax.cummax(ends, axis=0)
    moving_pos = jnp.where(valid, entry + rank, cs + entry)
    ids = jnp.zeros(cs + cm, jnp.int32).at[static_pos].set(static.gaussian_ids)
    ids = ids.at[moving_pos].set(moving.gaussian_ids + offset)
    return TileLists(ids, static.tile_start + moving.tile_start,
                     static.tile_count + moving.tile_count)


def _moving_lists(moving: Gaussians, K, world_to_camera, grid: TileGrid, moving_capacity: int,
                  config: RasterConfig):
    """The moving set projected and binned for camera K (3, 3), world_to_camera (4, 4):
    (projection, lists, needed () int32, entry depths (Cm,), +inf past the lists)."""
    proj = project_gaussians(moving, K, world_to_camera, width=grid.width, height=grid.height,
                             tile_size=config.tile_size, near=config.near)
    lists, needed = bin_gaussians(jax.lax.stop_gradient(proj), grid, moving_capacity)
    slot = jnp.arange(moving_capacity, dtype=jnp.int32)
    depths = jnp.where(slot < needed, jax.lax.stop_gradient(proj.depths)[lists.gaussian_ids], jnp.inf)
    return proj, lists, needed, depths


def rasterize_over_static(view: StaticView, moving: Gaussians, K, world_to_camera, *, width: int,
                          height: int, moving_capacity: int, background=None, features=None,
                          config: RasterConfig = RasterConfig()) -> RasterOutput:
    """Render the static Gaussians of ``view`` together with Nm moving Gaussians.

    view: ``static_view`` of the same camera K (3, 3), world_to_camera (4, 4) and config;
    moving_capacity: tile-intersection slots for the moving Gaussians; background (3,) or
    None; features (Nm, F) or None (F as the view's). Equals ``rasterize`` of [static, moving]
    (radii (Ns + Nm,)); ``num_intersections`` counts both sets, ``overflow`` says either
    set's lists did not fit.
    """
    grid = TileGrid(width, height, config.tile_size)
    dtype = view.params.dtype
    proj, lists, needed, depths = _moving_lists(moving, K, world_to_camera, grid, moving_capacity, config)
    if features is None:
        features = jnp.zeros((moving.num, view.params.shape[1] - base_columns(config.depth)), dtype)
    background = jnp.zeros(3, dtype) if background is None else jnp.asarray(background, dtype)
    ns = view.params.shape[0]
    merged = merge_tile_lists(grid, view.lists, view.depths, lists, depths, ns)
    params = jnp.concatenate([view.params, composite_params(proj, features, config.depth)], axis=0)
    acc, trans, steps, too_long = composite_rows(grid, config, params, merged)
    rgb, depth, alpha, feats = images_from_tiles(grid, acc, trans, background, config.depth)
    return RasterOutput(
        rgb=rgb, depth=depth, alpha=alpha, features=feats,
        radii=jnp.concatenate([view.radii, jax.lax.stop_gradient(proj.radii)]),
        num_visible=view.num_visible + jnp.sum(proj.visible, dtype=jnp.int32),
        num_intersections=view.needed + needed,
        max_tile_intersections=jnp.max(merged.tile_count),
        overflow=(needed > moving_capacity) | (view.needed > view.depths.shape[0]) | too_long,
        steps=steps,
        capacity=config.capacity,
    )


@pytree_dataclass
class TileUse:
    """How much of each capacity one ``rasterize_changed_tiles`` image needed (to size them)."""

    moving: jax.Array          # () int32 tile intersections of the moving set
    tiles: jax.Array           # () int32 tiles the moving set reaches (changed tiles)
    static_entries: jax.Array  # () int32 static entries in those tiles


def _tile_use(view: StaticView, lists: TileLists, needed) -> TileUse:
    """The ``TileUse`` of moving lists with needed () int32 intersections over ``view``: the
    tiles they reach and every static entry in those tiles (whether or not they fit)."""
    changed = lists.tile_count > 0
    return TileUse(needed, jnp.sum(changed, dtype=jnp.int32),
                   jnp.sum(jnp.where(changed, view.lists.tile_count, 0), dtype=jnp.int32))


def _changed_static(static: TileLists, static_depths, tiles, used, entry_capacity: int):
    """The static lists of the changed tiles, one after another: compact lists over the D
    tiles (D,) int32 (used (D,) bool; unused tiles get empty lists) in ``entry_capacity``
    slots, and their entry depths (from static_depths (Cs,))."""
    cs = static.gaussian_ids.shape[0]
    count = jnp.where(used, static.tile_count[tiles], 0)
    ends = jnp.cumsum(count, dtype=jnp.int32)
    start = ends - count
    slot = jnp.arange(entry_capacity, dtype=jnp.int32)
    tile = _run_of(start, entry_capacity)
    source = jnp.clip(static.tile_start[tiles[tile]] + slot - start[tile], 0, cs - 1)
    valid = slot < ends[-1]
    ids = jnp.where(valid, static.gaussian_ids[source], 0)
    depths = jnp.where(valid, static_depths[source], jnp.inf)
    # a tile cut by the capacity keeps what fits (the render is then marked as overflowing)
    fitted_start = jnp.minimum(start, entry_capacity)
    fitted = TileLists(ids, fitted_start, jnp.minimum(ends, entry_capacity) - fitted_start)
    return fitted, depths


def _strip_rows(grid: TileGrid, lists: TileLists, tiles, static_params, moving_params):
    """One parameter row per merged entry (ids ≥ Ns are moving rows), its centre shifted from
    the entry's image tile to its place in the strip: compact tile k sits at column k mod TX,
    row k div TX of a strip as wide as the image (TX tiles); tiles (D,) int32 the image tile of
    each compact tile (ascending, so k ≤ its tile: the shifted centres stay in the image's range);
    static_params (Ns, R), moving_params (Nm, R): rows of ``kernels.composite``."""
    ns, nm = static_params.shape[0], moving_params.shape[0]
    entries = lists.gaussian_ids.shape[0]
    ids = lists.gaussian_ids
    rows = jnp.where((ids < ns)[:, None], static_params[jnp.minimum(ids, ns - 1)],
                     moving_params[jnp.clip(ids - ns, 0, nm - 1)])
    compact = _run_of(lists.tile_start, entries)
    ts = grid.tile_size
    tx = grid.tiles_x
    # each compact tile's shift once, gathered per entry: no integer division per entry (when the
    # GPU built these rows too, the worlds' 1,024 × 4 frames at 640×480 on one H100 went from
    # 8,355–8,393 to 8,538 frames/s)
    k = jnp.arange(tiles.shape[0], dtype=jnp.int32)
    tile_shift = jnp.stack([(k % tx - tiles % tx) * ts, (k // tx - tiles // tx) * ts], axis=1).astype(rows.dtype)
    shift = tile_shift[compact]
    # built whole in one pass (an update of the centre columns in place copied every row again)
    return jnp.concatenate([rows[:, :2] + shift, rows[:, 2:]], axis=1)


def rasterize_changed_tiles(view: StaticView, moving: Gaussians, K, world_to_camera, *, width: int,
                            height: int, moving_capacity: int, tile_capacity: int, entry_capacity: int,
                            longest_static_run: int | None = None, background=None, features=None,
                            config: RasterConfig = RasterConfig()) -> tuple[RasterOutput, TileUse]:
    """``rasterize_over_static``'s image, compositing only the tiles the moving set reaches.

    view: ``static_view`` of the same camera K (3, 3), world_to_camera (4, 4) and config;
    moving (Nm Gaussians) with features (Nm, F) or None; background (3,) or None.
    Capacities: ``moving_capacity`` moving tile intersections, ``tile_capacity`` changed
    tiles, ``entry_capacity`` static entries in them; ``longest_static_run``: at least the
    view's longest tile list, or None (``merge_tile_lists``). Returns the ``RasterOutput`` (the same
    fields as ``rasterize_over_static``; ``steps`` counts the changed tiles' compositing, and
    ``overflow`` also says a changed-tile capacity was outgrown) and the ``TileUse``.
    With the Pallas compositor (a GPU's) it is not differentiable (``composite_two_sets``);
    ``rasterize_over_static`` is.
    """
    grid = TileGrid(width, height, config.tile_size)
    # the strip: whole rows of the image's width, at least tile_capacity tiles
    slots = -(-tile_capacity // grid.tiles_x) * grid.tiles_x
    strip = TileGrid(grid.tiles_x * config.tile_size, slots // grid.tiles_x * config.tile_size, config.tile_size)
    dtype = view.params.dtype
    proj, lists, needed, depths = _moving_lists(moving, K, world_to_camera, grid, moving_capacity, config)
    if features is None:
        features = jnp.zeros((moving.num, view.params.shape[1] - base_columns(config.depth)), dtype)
    background = jnp.zeros(3, dtype) if background is None else jnp.asarray(background, dtype)

    use = _tile_use(view, lists, needed)
    num_changed, static_needed = use.tiles, use.static_entries
    changed = lists.tile_count > 0
    tiles = jnp.nonzero(changed, size=slots, fill_value=0)[0].astype(jnp.int32)
    used = jnp.arange(slots, dtype=jnp.int32) < num_changed
    static, static_depths = _changed_static(view.lists, view.depths, tiles, used, entry_capacity)
    in_runs = jnp.minimum(lists.tile_start[-1] + lists.tile_count[-1], moving_capacity)
    moving_lists = TileLists(lists.gaussian_ids, jnp.where(used, lists.tile_start[tiles], in_runs),
                             jnp.where(used, lists.tile_count[tiles], 0))
    merged = merge_tile_lists(strip, static, static_depths, moving_lists, depths, view.params.shape[0],
                              longest_static_run)
    moving_params = composite_params(proj, features, config.depth)
    if config.resolved_compositor() == "pallas":
        # each list composites its image tile's pixels, reading the rows where they lie
        acc, trans, walked = composite_two_sets(grid, config.pallas, view.params, moving_params, merged, tiles)
        steps, too_long = jnp.max(walked), jnp.zeros((), bool)
    else:
        rows = _strip_rows(grid, merged, tiles, view.params, moving_params)
        entries = TileLists(jnp.arange(rows.shape[0], dtype=jnp.int32), merged.tile_start, merged.tile_count)
        acc, trans, steps, too_long = composite_rows(strip, config, rows, entries)

    # each image tile from its strip tile if it has one, else the static image (one gather)
    strip_tile = jnp.full(grid.num_tiles, -1, jnp.int32).at[jnp.where(used, tiles, grid.num_tiles)].set(
        jnp.arange(slots, dtype=jnp.int32), mode="drop")
    from_strip, strip_tile = strip_tile >= 0, jnp.maximum(strip_tile, 0)
    acc = jnp.where(from_strip[:, None, None], acc[strip_tile], view.acc)
    trans = jnp.where(from_strip[:, None], trans[strip_tile], view.trans)
    rgb, depth, alpha, feats = images_from_tiles(grid, acc, trans, background, config.depth)
    unchanged_longest = jnp.max(jnp.where(changed, 0, view.lists.tile_count))
    return RasterOutput(
        rgb=rgb, depth=depth, alpha=alpha, features=feats,
        radii=jnp.concatenate([view.radii, jax.lax.stop_gradient(proj.radii)]),
        num_visible=view.num_visible + jnp.sum(proj.visible, dtype=jnp.int32),
        num_intersections=view.needed + needed,
        max_tile_intersections=jnp.maximum(unchanged_longest, jnp.max(merged.tile_count)),
        overflow=((needed > moving_capacity) | (view.needed > view.depths.shape[0]) | too_long | view.too_long
                  | (num_changed > tile_capacity) | (static_needed > entry_capacity)),
        steps=steps,
        capacity=config.capacity,
    ), use


def changed_tile_use(view: StaticView, moving: Gaussians, K, world_to_camera, *, width: int, height: int,
                     moving_capacity: int, config: RasterConfig = RasterConfig()) -> TileUse:
    """The ``TileUse`` of ``rasterize_changed_tiles`` with the same arguments (K (3, 3),
    world_to_camera (4, 4)), without rendering:
    the moving set's tile intersections, the tiles they reach (counted from the entries that fit
    ``moving_capacity``) and the static entries in those tiles."""
    grid = TileGrid(width, height, config.tile_size)
    _, lists, needed, _ = _moving_lists(moving, K, world_to_camera, grid, moving_capacity, config)
    return _tile_use(view, lists, needed)
