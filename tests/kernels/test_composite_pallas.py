"""The Pallas compositor (interpret mode on the CPU) against the pure-JAX one: images and
gradients on tiny scenes, including empty tiles, one-Gaussian tiles, lists cut short by the
intersection capacity and a camera with every Gaussian behind it; and its kernels lower to
Triton (the GPU path) without a GPU."""

from __future__ import annotations

import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import export

from kernels.composite import TileGrid, TileLists
from kernels.composite_pallas import PallasSettings, composite_pallas, composite_pallas_forward, composite_two_sets
from kernels.gaussians import Gaussians
from kernels.project import project_gaussians
from kernels.raster import RasterConfig, bin_gaussians, composite_params, rasterize
from tests.kernels.test_raster import camera, random_scene

IMAGE_ATOL = 1e-6   # same float32 sums in another order (running products vs triangle product)
GRAD_RTOL = 1e-5    # gradients, relative to the largest entry of each group
WIDTH, HEIGHT = 40, 30  # 3 × 2 tiles, partial on both axes
CHUNK = 8           # small, so a tile list spans several chunks

JAX = RasterConfig(capacity=1 << 11, compositor="jax", chunk=CHUNK, slots=2)
PALLAS = RasterConfig(capacity=1 << 11, compositor="pallas",
                      pallas=PallasSettings(chunk=CHUNK, interpret=True))
# the other block orientation in each kernel than the defaults, and twice the default backward
# chunk
FLIPPED = dataclasses.replace(PALLAS, pallas=dataclasses.replace(
    PALLAS.pallas, forward_entries_major=not PALLAS.pallas.forward_entries_major,
    backward_entries_major=not PALLAS.pallas.backward_entries_major,
    backward_chunk=2 * PALLAS.pallas.backward_chunk))


def single_gaussian(K, w2c, n: int) -> Gaussians:
    """One small opaque Gaussian in front of the camera, inside one tile, and n − 1
    transparent ones (culled), so the scene has the shapes of the others."""
    rot, trans = np.asarray(w2c[:3, :3], np.float64), np.asarray(w2c[:3, 3], np.float64)
    pixel = np.array([8.0, 8.0, 1.0])  # the centre of tile (0, 0)
    cam = 2.0 * np.linalg.solve(np.asarray(K, np.float64), pixel)
    means = np.tile((cam - trans) @ rot, (n, 1))
    logits = np.full(n, -1e4)
    logits[0] = 2.0
    return Gaussians(means=jnp.asarray(means, jnp.float32),
                     quats=jnp.asarray(np.tile([1.0, 0.2, -0.1, 0.3], (n, 1)), jnp.float32),
                     log_scales=jnp.asarray(np.tile([-3.5, -3.8, -3.6], (n, 1)), jnp.float32),
                     opacity_logits=jnp.asarray(logits, jnp.float32),
                     sh=jnp.asarray(np.full((n, 16, 3), 0.4), jnp.float32))


def behind(g: Gaussians, w2c) -> Gaussians:
    """The same Gaussians mirrored behind the camera (view depth < 0)."""
    rot, trans = np.asarray(w2c[:3, :3], np.float64), np.asarray(w2c[:3, 3], np.float64)
    cam = np.asarray(g.means, np.float64) @ rot.T + trans
    cam[:, 2] = -np.abs(cam[:, 2]) - 0.05
    return g.replace(means=jnp.asarray((cam - trans) @ rot, jnp.float32))


def _loss(g, feats, bg, weights, K, w2c, config):
    out = rasterize(g, K, w2c, width=WIDTH, height=HEIGHT, background=bg, features=feats,
                    config=config)
    return (jnp.sum(weights[0] * out.rgb) + jnp.sum(weights[1] * out.depth)
            + jnp.sum(weights[2] * out.alpha) + jnp.sum(weights[3] * out.features))


# One program per config and shape, shared by every scene below (compiling dominates).
render = jax.jit(lambda g, f, b, K, w2c, config: rasterize(
    g, K, w2c, width=WIDTH, height=HEIGHT, background=b, features=f, config=config),
    static_argnums=5)
gradient = jax.jit(jax.grad(_loss, argnums=(0, 1, 2)), static_argnums=6)


@pytest.mark.parametrize("pallas", [PALLAS, FLIPPED], ids=["default_blocks", "flipped_blocks"])
def test_pallas_equals_jax_compositor(pallas):
    K, w2c = camera(WIDTH, HEIGHT)
    g, feats = random_scene(seed=5, n=120)
    bg = jnp.asarray([0.2, 0.5, 0.9], jnp.float32)
    rng = np.random.default_rng(0)
    weights = [jnp.asarray(rng.normal(size=s), jnp.float32) for s in
               [(HEIGHT, WIDTH, 3), (HEIGHT, WIDTH), (HEIGHT, WIDTH), (HEIGHT, WIDTH, 3)]]
    scenes = {"scene": g, "one_gaussian": single_gaussian(K, w2c, g.num),
              "all_behind": behind(g, w2c)}
    for name, gaussians in scenes.items():
        ref, got = (render(gaussians, feats, bg, K, w2c, c) for c in (JAX, pallas))
        for key in ("rgb", "depth", "alpha", "features"):
            np.testing.assert_allclose(getattr(got, key), getattr(ref, key), atol=IMAGE_ATOL,
                                       err_msg=f"{name} {key}")
        expected, grads = (gradient(gaussians, feats, bg, weights, K, w2c, c) for c in (JAX, pallas))
        for a, b in zip(jax.tree.leaves(grads), jax.tree.leaves(expected)):
            scale = float(jnp.max(jnp.abs(b)))
            np.testing.assert_allclose(a, b, atol=GRAD_RTOL * max(scale, 1e-6), err_msg=name)
        assert not bool(got.overflow)
        # What each case exercises.
        if name == "scene":  # the transmittance floor, lists over several chunks
            assert float(jnp.max(ref.alpha)) > 0.99 and int(ref.max_tile_intersections) > 2 * CHUNK
            assert float(jnp.max(jnp.abs(grads[0].means))) > 0
        elif name == "one_gaussian":  # one tile with one entry, five empty tiles
            assert int(ref.num_intersections) == 1 and float(jnp.max(ref.alpha)) > 0.3
        else:
            assert int(ref.num_visible) == 0
            np.testing.assert_array_equal(got.rgb, jnp.broadcast_to(bg, got.rgb.shape))


def test_lists_cut_by_the_capacity_composite_alike():
    """96 slots for a scene that needs 154: both keep the nearest 96 entries (the Pallas
    compositor also with its read-ahead)."""
    K, w2c = camera(WIDTH, HEIGHT)
    g, feats = random_scene(seed=5, n=120)
    bg = jnp.zeros(3, jnp.float32)
    read_ahead = dataclasses.replace(PALLAS, pallas=dataclasses.replace(PALLAS.pallas, prefetch=True))
    ref, got, got_read_ahead = (render(g, feats, bg, K, w2c, dataclasses.replace(c, capacity=96))
                                for c in (JAX, PALLAS, read_ahead))
    assert bool(ref.overflow) and bool(got.overflow) and int(ref.num_intersections) > 96 + 32
    for key in ("rgb", "depth", "alpha", "features"):
        np.testing.assert_allclose(getattr(got, key), getattr(ref, key), atol=IMAGE_ATOL, err_msg=key)
        np.testing.assert_allclose(getattr(got_read_ahead, key), getattr(ref, key), atol=IMAGE_ATOL,
                                   err_msg=f"read ahead {key}")


@jax.jit
def rows_and_lists(g, feats, K, w2c):
    """The compositor's rows of g (N Gaussians) with feats (N, F) and their tile lists (2,048
    slots), for a WIDTH × HEIGHT camera K (3, 3), w2c (4, 4)."""
    grid = TileGrid(WIDTH, HEIGHT)
    proj = project_gaussians(g, K, w2c, width=WIDTH, height=HEIGHT, tile_size=grid.tile_size)
    return composite_params(proj, feats), bin_gaussians(proj, grid, 1 << 11)[0]


def test_a_forward_without_last_contributors_composites_the_same_and_counts_its_chunks():
    """Rendered without differentiating, the forward tracks no last contributor (the backward's
    residual) and composites the same pixels; each tile's walked chunks cover its last
    contributor and end when its pixels saturate (both with and without reading ahead)."""
    K, w2c = camera(WIDTH, HEIGHT)
    g, feats = random_scene(seed=5, n=120)
    # larger and more opaque: every tile's pixels saturate before its list ends
    g = g.replace(opacity_logits=jnp.full_like(g.opacity_logits, 3.0), log_scales=g.log_scales + 2.0)
    grid = TileGrid(WIDTH, HEIGHT)
    params, lists = rows_and_lists(g, feats, K, w2c)
    count = np.asarray(lists.tile_count)
    forward = jax.jit(composite_pallas_forward, static_argnums=(0, 1), static_argnames=("with_last",))
    for prefetch in (False, True):
        settings = dataclasses.replace(PALLAS.pallas, prefetch=prefetch)
        acc, trans, walked, last = forward(grid, settings, params, lists)
        acc_only, trans_only, walked_only, none = forward(grid, settings, params, lists, with_last=False)
        assert none is None
        np.testing.assert_array_equal(acc_only, acc)
        np.testing.assert_array_equal(trans_only, trans)
        np.testing.assert_array_equal(walked_only, walked)
        walked = np.asarray(walked)
        assert np.all(walked * CHUNK >= np.asarray(last).max(axis=1))   # each tile reached its last contributor
        # and stopped once its pixels saturated, a few chunks in and before its list's end
        assert np.all(walked < -(-count // CHUNK)) and np.all(walked > 1)
        # the custom-VJP primal (no gradient) reports the longest tile's walk
        _, _, steps = jax.jit(composite_pallas, static_argnums=(0, 1))(grid, settings, params, lists.gaussian_ids,
                                                                       lists.tile_start, lists.tile_count)
        assert int(steps) == walked.max()


def test_two_sets_composite_as_their_joined_rows_at_the_chosen_tiles():
    """Rows read from two sets where they lie, each list over the pixels of the image tile it
    names: the same sums as the forward over the joined rows at those tiles, bit for bit, at
    any split of the rows, with and without reading ahead; under vmap the first set may be
    shared (unbatched); and no gradient is pretended."""
    K, w2c = camera(WIDTH, HEIGHT)
    g, feats = random_scene(seed=5, n=120)
    grid = TileGrid(WIDTH, HEIGHT)
    params, lists = rows_and_lists(g, feats, K, w2c)
    tiles = jnp.array([3, 1, 4, 0], jnp.int32)  # out of order; the last list left empty
    count = lists.tile_count[tiles].at[3].set(0)
    assert np.all(np.asarray(count[:3]) > CHUNK)
    chosen = TileLists(lists.gaussian_ids, lists.tile_start[tiles], count)
    # splits at ids the chosen lists hold: that id is then the second set's first row
    ids = np.asarray(lists.gaussian_ids)
    present = np.unique(np.concatenate([ids[start:start + n] for start, n in
                                        zip(np.asarray(chosen.tile_start[:3]), np.asarray(count[:3]))]))
    splits = (int(present[1]), int(present[len(present) // 2]), int(present[-1]))
    two_sets = jax.jit(composite_two_sets, static_argnums=(0, 1))
    for prefetch in (False, True):
        settings = dataclasses.replace(PALLAS.pallas, prefetch=prefetch)
        acc, trans, walked_all, _ = composite_pallas_forward(grid, settings, params, lists, with_last=False)
        for split in splits:
            got_acc, got_trans, walked = two_sets(grid, settings, params[:split], params[split:], chosen, tiles)
            np.testing.assert_array_equal(got_acc[:3], acc[tiles[:3]], err_msg=f"{prefetch} {split}")
            np.testing.assert_array_equal(got_trans[:3], trans[tiles[:3]], err_msg=f"{prefetch} {split}")
            np.testing.assert_array_equal(walked[:3], walked_all[tiles[:3]])
            np.testing.assert_array_equal(got_acc[3], 0.0)
            np.testing.assert_array_equal(got_trans[3], 1.0)
            assert int(walked[3]) == 0

    # many worlds over one static set: the first set unbatched; the second, the lists and their
    # tiles per world
    split = splits[1]
    dimmer = params[split:].at[:, 5].multiply(0.5)  # the moving rows' opacities halved
    other_tiles = jnp.array([4, 3, 1, 0], jnp.int32)
    other = TileLists(lists.gaussian_ids, lists.tile_start[other_tiles], lists.tile_count[other_tiles].at[3].set(0))
    batched = jax.jit(jax.vmap(lambda second, chosen, tiles: composite_two_sets(grid, PALLAS.pallas, params[:split],
                                                                                second, chosen, tiles)))
    worlds = ((params[split:], chosen, tiles), (dimmer, other, other_tiles))
    acc_b, trans_b, _ = batched(*jax.tree.map(lambda *x: jnp.stack(x), *worlds))
    for world, args in enumerate(worlds):
        acc_w, trans_w, _ = two_sets(grid, PALLAS.pallas, params[:split], *args)
        np.testing.assert_array_equal(acc_b[world], acc_w)
        np.testing.assert_array_equal(trans_b[world], trans_w)
    assert not np.array_equal(acc_b[0], acc_b[1])
    with pytest.raises(NotImplementedError, match="no backward"):
        jax.grad(lambda second: jnp.sum(composite_two_sets(grid, PALLAS.pallas, params[:split], second,
                                                           chosen, tiles)[0]))(params[split:])


@pytest.mark.parametrize("field", ["chunk", "backward_chunk", "num_warps", "backward_num_warps"])
@pytest.mark.parametrize("value", [0, 3, 6])
def test_settings_want_powers_of_two(field, value):
    """Chunks and warp counts that are not powers of two are refused, naming the field."""
    with pytest.raises(ValueError, match=f"PallasSettings.{field}: {value}"):
        PallasSettings(**{field: value})


@pytest.mark.parametrize("entries_major", [False, True])
def test_kernels_lower_to_triton(entries_major):
    """Forward and backward kernels lower to Triton for a CUDA target (no GPU needed), in
    either block orientation, each launched with its own warp count."""
    grid = TileGrid(WIDTH, HEIGHT)
    settings = PallasSettings(chunk=16, backward_chunk=8, num_warps=4, backward_num_warps=2,
                              forward_entries_major=entries_major,
                              backward_entries_major=entries_major)
    n, capacity = 64, 512

    def loss(params, ids, start, count):
        acc, trans, _ = composite_pallas(grid, settings, params, ids, start, count)
        return jnp.sum(acc) + jnp.sum(trans)

    args = (jax.ShapeDtypeStruct((n, 11), jnp.float32), jax.ShapeDtypeStruct((capacity,), jnp.int32),
            jax.ShapeDtypeStruct((grid.num_tiles,), jnp.int32),
            jax.ShapeDtypeStruct((grid.num_tiles,), jnp.int32))
    exported = export.export(jax.jit(jax.value_and_grad(loss)), platforms=["cuda"],
                             disabled_checks=[export.DisabledSafetyCheck.custom_call(
                                 "__gpu$xla.gpu.triton")])(*args)
    module = exported.mlir_module()
    assert re.findall(r'name = "composite_forward"[^}]*num_warps = (\d+)', module) == ["4"]
    assert re.findall(r'name = "composite_backward"[^}]*num_warps = (\d+)', module) == ["2"]
    # and the forward of a render that is not differentiated (no last contributors)
    forward_only = export.export(jax.jit(lambda *a: composite_pallas(grid, settings, *a)), platforms=["cuda"],
                                 disabled_checks=[export.DisabledSafetyCheck.custom_call(
                                     "__gpu$xla.gpu.triton")])(*args)
    assert re.findall(r'name = "composite_forward"[^}]*num_warps = (\d+)', forward_only.mlir_module()) == ["4"]
    # and the forward over two sets of rows (the batched worlds' changed tiles)
    # with the batched worlds' settings (chunks of 16 read ahead)
    worlds = dataclasses.replace(settings, prefetch=True)
    two_sets = export.export(
        jax.jit(lambda first, second, ids, start, count, tiles: composite_two_sets(
            grid, worlds, first, second, TileLists(ids, start, count), tiles)), platforms=["cuda"],
        disabled_checks=[export.DisabledSafetyCheck.custom_call("__gpu$xla.gpu.triton")])(
        jax.ShapeDtypeStruct((n, 11), jnp.float32), jax.ShapeDtypeStruct((n // 2, 11), jnp.float32), *args[1:],
        jax.ShapeDtypeStruct((grid.num_tiles,), jnp.int32))
    assert re.findall(r'name = "composite_forward_two_sets"[^}]*num_warps = (\d+)',
                      two_sets.mlir_module()) == ["4"]
