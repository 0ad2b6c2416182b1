"""Rendering a scene whose Gaussians are mostly static: bin the static set once per camera,
merge the moving set into its tile lists per render.

For many simulated worlds of one scene seen by the same cameras, most Gaussians (the
background) are identical in every world; only the Gaussians attached to bodies move. So,
per camera, ``static_view`` projects the static Gaussians, evaluates their SH colour and
bins them into depth-sorted tile lists once; per world, ``rasterize_over_static`` projects
and bins only the moving Gaussians and merges their lists into the static ones by depth
(per tile, a merge of two sorted lists by rank: a binary search of each moving entry in its
tile's static run, and a cumulative count for the static entries), then composites the
merged lists with the usual compositor. The result is the image ``kernels.raster.rasterize``
gives for the concatenation [static, moving]: one depth order per pixel, ties broken as its
stable sort breaks them (static first, then by index).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from kernels.composite import TileGrid, TileLists
from kernels.gaussians import Gaussians
from kernels.project import project_gaussians
from kernels.pytree import pytree_dataclass
from kernels.raster import (RasterConfig, RasterOutput, base_columns, bin_gaussians, composite_params,
                            composite_rows, images_from_tiles)


@pytree_dataclass
class StaticView:
    """The static Gaussians as one camera sees them, projected, coloured and binned."""

    params: jax.Array       # (Ns, D) rows of kernels.composite
    lists: TileLists        # their tile lists, sorted by (tile, depth); capacity Cs
    depths: jax.Array       # (Cs,) view depth of each sorted entry, +inf past the lists
    needed: jax.Array       # () int32 tile intersections needed (> Cs: lists incomplete)
    radii: jax.Array        # (Ns,) 3σ screen radius, 0 where culled
    num_visible: jax.Array  # () int32


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
    return StaticView(composite_params(proj, features, config.depth), lists, depths, needed, proj.radii,
                      jnp.sum(proj.visible, dtype=jnp.int32))


def merge_tile_lists(grid: TileGrid, static: TileLists, static_depths, moving: TileLists, moving_depths,
                     offset: int) -> TileLists:
    """Merge two (tile, depth)-sorted lists into one; static first where depths are equal.

    static: lists of capacity Cs with static_depths (Cs,) sorted entry depths; moving: lists of
    capacity Cm with moving_depths (Cm,) (the entries in its tiles' runs come first); ``offset``
    is added to the moving Gaussian ids (their rows follow the static rows). Returns lists of
    capacity Cs + Cm.
    """
    cs = static.gaussian_ids.shape[0]
    cm = moving.gaussian_ids.shape[0]
    entry = jnp.arange(cm, dtype=jnp.int32)
    # the entries in a tile's run (binning leaves out the tiles a Gaussian's α never reaches)
    valid = entry < jnp.minimum(moving.tile_start[-1] + moving.tile_count[-1], cm)
    # Each moving entry's tile: the sorted entries' tile runs start at moving.tile_start.
    bounds = jnp.concatenate([moving.tile_start, jnp.full((1,), cm, jnp.int32)])
    tile = jnp.clip(jnp.searchsorted(bounds, entry, side="right").astype(jnp.int32) - 1,
                    0, grid.num_tiles - 1)
    # Rank among the static entries: everything before its tile's run plus the run's
    # entries with depth ≤ its own (lower bound of "depth > d" by bisection).
    lo = static.tile_start[tile]
    hi = lo + static.tile_count[tile]

    def bisect(_, bounds_):
        lo_, hi_ = bounds_
        mid = (lo_ + hi_) // 2
        right = (mid < hi_) & (static_depths[jnp.minimum(mid, cs - 1)] <= moving_depths)
        return jnp.where(right, mid + 1, lo_), jnp.where(right, hi_, mid)

    steps = max(1, int(cs).bit_length())
    rank, _ = jax.lax.fori_loop(0, steps, bisect, (lo, hi))
    rank = jnp.where(valid, rank, cs)
    # A static entry moves back by the number of moving entries ranked at or before it.
    inserted = jnp.zeros(cs + 1, jnp.int32).at[rank].add(valid.astype(jnp.int32))
    static_pos = jnp.arange(cs, dtype=jnp.int32) + jnp.cumsum(inserted)[:cs]
    moving_pos = jnp.where(valid, entry + rank, cs + entry)
    ids = jnp.zeros(cs + cm, jnp.int32).at[static_pos].set(static.gaussian_ids)
    ids = ids.at[moving_pos].set(moving.gaussian_ids + offset)
    return TileLists(ids, static.tile_start + moving.tile_start,
                     static.tile_count + moving.tile_count)


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
    proj = project_gaussians(moving, K, world_to_camera, width=width, height=height,
                             tile_size=config.tile_size, near=config.near)
    if features is None:
        features = jnp.zeros((moving.num, view.params.shape[1] - base_columns(config.depth)), dtype)
    background = jnp.zeros(3, dtype) if background is None else jnp.asarray(background, dtype)
    lists, needed = bin_gaussians(jax.lax.stop_gradient(proj), grid, moving_capacity)
    slot = jnp.arange(moving_capacity, dtype=jnp.int32)
    depths = jnp.where(slot < needed, jax.lax.stop_gradient(proj.depths)[lists.gaussian_ids],
                       jnp.inf)
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
