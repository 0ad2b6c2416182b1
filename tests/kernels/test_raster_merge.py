"""Static Gaussians binned once, moving ones merged per render: the same image, lists and
diagnostics as rasterizing the concatenation, including exact depth ties, a moving set
entirely behind the camera and moving lists that overflow their capacity."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kernels.composite import TileGrid, TileLists
from kernels.composite_pallas import PallasSettings
from kernels.gaussians import Gaussians, concatenate
from kernels.raster import RasterConfig, rasterize
from kernels.raster_merge import merge_tile_lists, rasterize_changed_tiles, rasterize_over_static, static_view
from tests.kernels.test_composite_pallas import behind
from tests.kernels.test_raster import camera, random_scene

WIDTH, HEIGHT = 40, 30
NUM_STATIC = 80
CONFIG = RasterConfig(capacity=1 << 11, chunk=8, slots=2)
MOVING_CAPACITY = 1 << 9
IMAGE_ATOL = 1e-6  # the same float32 arithmetic, compiled into different programs

full_render = jax.jit(lambda g, f, K, w2c: rasterize(
    g, K, w2c, width=WIDTH, height=HEIGHT, background=jnp.ones(3) * 0.3, features=f,
    config=CONFIG))
view_of = jax.jit(lambda g, f, K, w2c: static_view(g, K, w2c, width=WIDTH, height=HEIGHT,
                                                   features=f, config=CONFIG))


merged = jax.jit(lambda v, g, f, K, w2c, capacity: rasterize_over_static(
    v, g, K, w2c, width=WIDTH, height=HEIGHT, moving_capacity=capacity,
    background=jnp.ones(3) * 0.3, features=f, config=CONFIG), static_argnums=5)


def merged_render(view, g, f, K, w2c, capacity=MOVING_CAPACITY):
    return merged(view, g, f, K, w2c, capacity)


def split(g: Gaussians, feats):
    static = jax.tree.map(lambda x: x[:NUM_STATIC], g)
    moving = jax.tree.map(lambda x: x[NUM_STATIC:], g)
    return static, moving, feats[:NUM_STATIC], feats[NUM_STATIC:]


def _random_lists(rng, num_tiles: int, most: int, spare: int, ids, depths_from):
    """Tile lists of up to ``most`` entries a tile (some empty), depth-sorted within each tile,
    with ``spare`` slots after the runs: (lists, entry depths (+inf in the spare slots), per-tile
    (depth, id) runs)."""
    counts = rng.integers(0, most + 1, num_tiles)
    counts[1] = 0
    runs = [sorted(zip(rng.choice(depths_from, n), rng.choice(ids, n, replace=False)), key=lambda e: e[0])
            for n in counts]
    flat = [e for run in runs for e in run]
    depths = np.array([d for d, _ in flat] + [np.inf] * spare, np.float32)
    gaussian_ids = np.array([i for _, i in flat] + [0] * spare, np.int32)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int32)
    return TileLists(jnp.asarray(gaussian_ids), jnp.asarray(starts), jnp.asarray(counts, np.int32)), depths, runs


@pytest.mark.parametrize("bounded", [False, True], ids=["bisect_the_capacity", "bisect_the_longest_run"])
def test_merging_lists_is_a_stable_sort_of_each_tile(bounded):
    """``merge_tile_lists`` against a sort per tile: each tile's static and moving entries by
    depth, static before moving where depths are equal (drawn from a few values: many ties), each
    set in its own order; tiles with no entry of either set; spare slots after both lists."""
    rng = np.random.default_rng(3)
    grid = TileGrid(64, 48)  # 4 × 3 tiles
    offset = 100
    depth_values = np.array([0.5, 1.0, 1.25, 2.0, 3.0], np.float32)
    static, static_depths, static_runs = _random_lists(rng, grid.num_tiles, 9, 5, np.arange(offset), depth_values)
    moving, moving_depths, moving_runs = _random_lists(rng, grid.num_tiles, 4, 3, np.arange(40), depth_values)
    longest = int(static.tile_count.max()) if bounded else None
    merged = jax.jit(merge_tile_lists, static_argnums=(0, 5, 6))(
        grid, static, jnp.asarray(static_depths), moving, jnp.asarray(moving_depths), offset, longest)
    expected = []
    for s_run, m_run in zip(static_runs, moving_runs):
        entries = [(d, 0, k, i) for k, (d, i) in enumerate(s_run)] + [(d, 1, k, i + offset)
                                                                     for k, (d, i) in enumerate(m_run)]
        expected += [i for *_, i in sorted(entries)]
    total = len(expected)
    assert merged.gaussian_ids.shape == (static_depths.size + moving_depths.size,)
    np.testing.assert_array_equal(merged.gaussian_ids[:total], expected)
    np.testing.assert_array_equal(merged.tile_count, static.tile_count + moving.tile_count)
    np.testing.assert_array_equal(merged.tile_start, static.tile_start + moving.tile_start)
    ties = sum(len({d for d, _ in s} & {d for d, _ in m}) for s, m in zip(static_runs, moving_runs))
    assert ties > 0 and int(jnp.sum((static.tile_count == 0) & (moving.tile_count == 0))) >= 1


def test_merged_lists_render_the_concatenation():
    K, w2c = camera(WIDTH, HEIGHT)
    g, feats = random_scene(seed=7, n=120)
    static, moving, f_static, f_moving = split(g, feats)
    # Exact depth ties between the sets: moving Gaussians on top of static ones.
    moving = moving.replace(means=moving.means.at[:6].set(static.means[10:16]))
    view = view_of(static, f_static, K, w2c)
    cases = {"moving": moving, "moving_behind_the_camera": behind(moving, w2c)}
    for name, mov in cases.items():
        ref = full_render(concatenate([static, mov]), feats, K, w2c)
        got = merged_render(view, mov, f_moving, K, w2c)
        for key in ("rgb", "depth", "alpha", "features", "radii"):
            np.testing.assert_allclose(getattr(got, key), getattr(ref, key), atol=IMAGE_ATOL,
                                       err_msg=f"{name} {key}")
        for key in ("num_visible", "num_intersections", "max_tile_intersections", "overflow"):
            assert int(getattr(got, key)) == int(getattr(ref, key)), (name, key)
    static_only = full_render(static, f_static, K, w2c)
    np.testing.assert_allclose(static_only.rgb, ref.rgb, atol=IMAGE_ATOL)  # moving set behind
    # the moving set did change the first image
    first = full_render(concatenate([static, moving]), feats, K, w2c)
    assert float(jnp.max(jnp.abs(first.rgb - ref.rgb))) > 0.05


def test_moving_overflow_is_reported():
    K, w2c = camera(WIDTH, HEIGHT)
    g, feats = random_scene(seed=7, n=120)
    static, moving, f_static, f_moving = split(g, feats)
    view = view_of(static, f_static, K, w2c)
    fits = merged_render(view, moving, f_moving, K, w2c)
    cut = merged_render(view, moving, f_moving, K, w2c, capacity=8)
    needed = int(fits.num_intersections - view.needed)
    assert not bool(fits.overflow) and needed > 8
    assert bool(cut.overflow) and int(cut.num_intersections) == int(fits.num_intersections)


# --- only the changed tiles composited -------------------------------------------------------

STRIP_WIDTH, STRIP_HEIGHT = 100, 70  # 7 × 5 tiles, the last column and row partial
STRIP_CONFIGS = {
    "jax": CONFIG,
    "pallas": RasterConfig(capacity=1 << 11, compositor="pallas",
                           pallas=PallasSettings(chunk=8, interpret=True)),
}


@functools.cache  # one jitted function per config: its programs are reused across tests
def _strip_full(config):
    return jax.jit(lambda g, f, K, w2c: rasterize(
        g, K, w2c, width=STRIP_WIDTH, height=STRIP_HEIGHT, background=jnp.ones(3) * 0.3, features=f,
        config=config))


@functools.cache  # one jitted function per config: its programs are reused across tests
def _strip_view(config):
    return jax.jit(lambda g, f, K, w2c: static_view(g, K, w2c, width=STRIP_WIDTH, height=STRIP_HEIGHT,
                                                    features=f, config=config))


@functools.cache  # one jitted function per config: its programs are reused across tests
def _strip_changed(config):
    return jax.jit(lambda v, g, f, K, w2c, tiles, entries, longest=None: rasterize_changed_tiles(
        v, g, K, w2c, width=STRIP_WIDTH, height=STRIP_HEIGHT, moving_capacity=MOVING_CAPACITY,
        tile_capacity=tiles, entry_capacity=entries, longest_static_run=longest,
        background=jnp.ones(3) * 0.3, features=f, config=config), static_argnums=(5, 6, 7))


def strip_scene():
    """A static set and a small moving set that reaches some of the tiles, not all."""
    K, w2c = camera(STRIP_WIDTH, STRIP_HEIGHT)
    g, feats = random_scene(seed=11, n=160)
    static, moving = jax.tree.map(lambda x: x[:NUM_STATIC], g), jax.tree.map(lambda x: x[NUM_STATIC:], g)
    keep = np.arange(moving.num)[::9]  # a few, made small: a handful of tiles
    moving = jax.tree.map(lambda x: x[keep], moving)
    moving = moving.replace(log_scales=moving.log_scales - 1.0)
    # exact depth ties with static Gaussians
    moving = moving.replace(means=moving.means.at[:2].set(static.means[20:22]))
    return K, w2c, static, moving, feats[:NUM_STATIC], feats[NUM_STATIC:][keep]


# "jax": the JAX compositor over a strip of gathered rows (the CPU's path); "pallas": the
# two-set compositor reading the rows where they lie (a GPU's path, interpreted here)
@pytest.mark.parametrize("name", ["jax", "pallas"])
def test_changed_tiles_render_the_concatenation(name):
    K, w2c, static, moving, f_static, f_moving = strip_scene()
    num_tiles = 7 * 5
    config = STRIP_CONFIGS[name]
    view = _strip_view(config)(static, f_static, K, w2c)
    ref = _strip_full(config)(concatenate([static, moving]), jnp.concatenate([f_static, f_moving]), K, w2c)
    got, use = _strip_changed(config)(view, moving, f_moving, K, w2c, num_tiles, 1 << 11)
    assert 0 < int(use.tiles) < num_tiles, (name, int(use.tiles))
    assert 0 < int(use.static_entries) < int(view.needed), name
    for key in ("rgb", "depth", "alpha", "features", "radii"):
        np.testing.assert_allclose(getattr(got, key), getattr(ref, key), atol=1e-5, err_msg=f"{name} {key}")
    for key in ("num_visible", "num_intersections", "max_tile_intersections", "overflow"):
        assert int(getattr(got, key)) == int(getattr(ref, key)), (name, key)


def test_changed_tiles_within_tight_capacities_and_a_bounded_bisection():
    """The capacities and the bisection bound act before the compositor: checked on one."""
    K, w2c, static, moving, f_static, f_moving = strip_scene()
    num_tiles = 7 * 5
    view = _strip_view(CONFIG)(static, f_static, K, w2c)
    got, use = _strip_changed(CONFIG)(view, moving, f_moving, K, w2c, num_tiles, 1 << 11)
    # capacities just large enough give the same image; the unchanged tiles are the static image
    tight, _ = _strip_changed(CONFIG)(view, moving, f_moving, K, w2c, int(use.tiles), int(use.static_entries))
    np.testing.assert_allclose(tight.rgb, got.rgb, atol=1e-6)
    assert not bool(tight.overflow)
    # the bisection bounded by the longest static list (fewer steps): the same image
    longest = int(np.max(view.lists.tile_count))
    assert longest.bit_length() < view.depths.shape[0].bit_length()
    bounded, _ = _strip_changed(CONFIG)(view, moving, f_moving, K, w2c, num_tiles, 1 << 11, longest)
    np.testing.assert_array_equal(bounded.rgb, got.rgb)
    alone = _strip_full(CONFIG)(static, f_static, K, w2c)
    same = np.all(np.abs(np.asarray(got.rgb) - np.asarray(alone.rgb)) < 1e-6, axis=-1)
    assert 0 < same.mean() < 1


def test_changed_tiles_with_no_moving_gaussian_in_view():
    K, w2c, static, moving, f_static, f_moving = strip_scene()
    view = _strip_view(CONFIG)(static, f_static, K, w2c)
    got, use = _strip_changed(CONFIG)(view, behind(moving, w2c), f_moving, K, w2c, 4, 64)
    alone = _strip_full(CONFIG)(static, f_static, K, w2c)
    assert int(use.tiles) == 0 and int(use.static_entries) == 0 and not bool(got.overflow)
    np.testing.assert_allclose(got.rgb, alone.rgb, atol=1e-6)


def test_changed_tile_overflow_is_reported():
    K, w2c, static, moving, f_static, f_moving = strip_scene()
    view = _strip_view(CONFIG)(static, f_static, K, w2c)
    _, use = _strip_changed(CONFIG)(view, moving, f_moving, K, w2c, 35, 1 << 11)
    tiles, entries = int(use.tiles), int(use.static_entries)
    few_tiles, use_a = _strip_changed(CONFIG)(view, moving, f_moving, K, w2c, tiles - 1, 1 << 11)
    few_entries, use_b = _strip_changed(CONFIG)(view, moving, f_moving, K, w2c, 35, entries - 1)
    assert bool(few_tiles.overflow) and bool(few_entries.overflow)
    # what was needed is still counted, so the caller can grow the capacity that was outgrown
    assert (int(use_a.tiles), int(use_b.static_entries)) == (tiles, entries)


def test_changed_tiles_keep_the_image_precision_when_every_tile_changes():
    """The strip is as wide as the image, so the shifted centres keep the image's float32
    precision: a strip one tile high would move them up to (tiles × 16) px away."""
    width, height = 256, 160
    K, w2c = camera(width, height)
    g, feats = random_scene(seed=5, n=2000, spread=2.0)
    take = lambda x, part: x[part::2]  # noqa: E731
    static, moving = jax.tree.map(lambda x: take(x, 0), g), jax.tree.map(lambda x: take(x, 1), g)
    config = RasterConfig(capacity=1 << 16, chunk=16, slots=8)
    view = jax.jit(lambda g, f: static_view(g, K, w2c, width=width, height=height, features=f, config=config))(
        static, take(feats, 0))
    kwargs = dict(width=width, height=height, moving_capacity=1 << 15, config=config)
    got, use = jax.jit(lambda v, g, f: rasterize_changed_tiles(v, g, K, w2c, tile_capacity=160, entry_capacity=1 << 16,
                                                               features=f, **kwargs))(view, moving, take(feats, 1))
    ref = jax.jit(lambda v, g, f: rasterize_over_static(v, g, K, w2c, features=f, **kwargs))(view, moving, take(feats, 1))
    assert int(use.tiles) > 130 and not bool(got.overflow) and not bool(ref.overflow)
    np.testing.assert_allclose(got.rgb, ref.rgb, atol=1e-6)


def test_a_background_tile_longer_than_the_scan_is_reported():
    """With the autodiff backward a tile list longer than its scan is incomplete: in a tile no
    moving Gaussian reaches it is the background's own composite that is cut, and it is said."""
    K, w2c, static, moving, f_static, f_moving = strip_scene()
    base = _strip_view(CONFIG)(static, f_static, K, w2c)
    _, use = _strip_changed(CONFIG)(base, moving, f_moving, K, w2c, 35, 1 << 11)
    longest = int(np.max(base.lists.tile_count))
    config = RasterConfig(capacity=1 << 11, chunk=1, slots=2, backward="autodiff", tile_capacity=longest - 1)
    view = _strip_view(config)(static, f_static, K, w2c)
    got, _ = _strip_changed(config)(view, moving, f_moving, K, w2c, 35, 1 << 11)
    ref = merged_render_with(config)(view, moving, f_moving, K, w2c)
    assert bool(view.too_long) and bool(got.overflow) and bool(ref.overflow)
    np.testing.assert_allclose(got.rgb, ref.rgb, atol=1e-5)


@functools.cache  # one jitted function per config: its programs are reused across tests
def merged_render_with(config):
    return jax.jit(lambda v, g, f, K, w2c: rasterize_over_static(
        v, g, K, w2c, width=STRIP_WIDTH, height=STRIP_HEIGHT, moving_capacity=MOVING_CAPACITY,
        background=jnp.ones(3) * 0.3, features=f, config=config))
