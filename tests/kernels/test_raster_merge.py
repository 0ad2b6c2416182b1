"""Static Gaussians binned once, moving ones merged per render: the same image, lists and
diagnostics as rasterizing the concatenation, including exact depth ties, a moving set
entirely behind the camera and moving lists that overflow their capacity."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from kernels.gaussians import Gaussians, concatenate
from kernels.raster import RasterConfig, rasterize
from kernels.raster_merge import rasterize_over_static, static_view
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
