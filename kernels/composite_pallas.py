"""Per-tile front-to-back compositing as Pallas kernels: the GPU path of ``kernels.composite``.

Same inputs, rules and outputs as ``kernels.composite.composite``: parameter rows (N, D) =
[μx, μy, a, b, c, opacity, features...] and depth-sorted tile lists (``TileLists``). One
program per tile, its P = T×T pixels one block: the tile's list is walked in chunks of B
entries, each composited as a (B, P) or (P, B) block (``PallasSettings``) whose running
transmittances are the running products of (1 − α) along the chunk (one scan of
multiplications, no per-entry loop; ``kernels.running_product``), until
every pixel is saturated or the list ends. A render that is not differentiated tracks no
pixel's last contributor (only the backward needs it). A GPU runs the tiles as independent
programs, so each stops after its own work and no work queue is needed
(``kernels.composite`` needs one to get the same early exit inside one XLA loop).

The custom VJP walks each tile back to front from its last contributor, recovering Tᵢ by
division as 3DGS does (safe: α ≤ 0.99 and T ≥ 1e-4), reduces each entry's gradient over the
tile's pixels and adds it to its Gaussian's row with atomic adds (the order of those float
additions varies from run to run: gradients agree to rounding, not bit for bit).

``composite_two_sets`` runs the same forward walk over lists whose entries' rows lie in two
sets (a static set shared by many renders and a moving set of each) and whose pixels are those
of any image tile named per list: the batched worlds' changed tiles, composited with no copy of
their rows (``kernels.raster_merge.rasterize_changed_tiles``). It has no backward.

Lowered through Triton on a GPU; ``interpret=True`` runs the same kernel bodies on any
backend (the CPU tests compare them with ``kernels.composite``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from functools import partial

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plgpu

from kernels.composite import ALPHA_MAX, NUM_GEOMETRY, T_MIN, TileGrid, TileLists
from kernels.project import ALPHA_MIN
from kernels.running_product import running_products

# Each entry's Gaussian is a power of 2: an NVIDIA GPU computes 2^x with one special-function
# instruction (ex2.approx: relative error about 2⁻²²), where e^x is a library routine of many
# instructions. The running transmittances are products (``kernels.running_product``): no
# logarithm, no power.
LOG2_E = 1.4426950408889634


@dataclasses.dataclass(frozen=True)
class PallasSettings:
    """Static settings of the Pallas compositor (hashable: part of the program's key).

    chunk, backward_chunk: list entries composited per step (B, a power of two) in the
        forward and the backward. Larger chunks mean fewer loop steps but more wasted work
        after a tile saturates and more registers. The backward walks only up to each tile's
        last contributor (no saturated tail). On an H100, 1.4M Gaussians at 1920×1080
        (``experiments/bench_render_backward.py``): 8 took forward+backward from 4.99 to
        4.76 ms against 16, 4 was no faster, 32 twice as slow. At a training view's scale
        the better chunk depends on the scene, by up to 7 %: garden's cameras (138K, 648×420)
        8 as fast or faster, 100K random Gaussians at 640×480 16 faster by 7 %, the snowmiku
        capture (238K, 1000×750) 16 faster by 2.5–4.4 % (loss gradient); training keeps 16
        (``phirie_jax.capture.train.TRAINING_RASTER``).
    num_warps, backward_num_warps: warps per tile program (Triton) of the forward and the
        backward kernel (a power of two). The backward uses 255 registers a thread at 4
        warps (12.5 % occupancy on an H100), yet at 1080p 2, 8 or 16 warps took
        forward+backward 6–67 % longer than 4 at backward chunks 8 and 16 (8 warps beat 4
        only at chunk 32, itself slower): 4 for both.
    prefetch: load each chunk's list entries two steps and its parameter rows one step
        before they are composited, so the two dependent memory reads overlap the work of
        the chunks before. Measured on an H100 (compositor alone, garden, garden ×10 at
        1080p, random 100K): from 2 % faster to 11 % slower, so off by default. Where the
        rows lay one after another (the batched worlds' changed tiles, when a strip of rows
        was built for them) it was 5 % faster; not re-measured since they are read where they
        lie (``composite_two_sets``).
    forward_entries_major, backward_entries_major: lay each chunk out as a (B, P) block
        (entries × pixels) rather than (P, B) in the forward and the backward kernel.
        Triton spreads a block's last axis over a warp's threads, so entries-major keeps a
        chunk's B entries of a pixel in one thread's registers: the running transmittance
        (a cumulative sum along the entries) needs no shuffles, and a per-pixel vector has
        the same layout as the block's pixel axis (no conversions through shared memory).
        Measured on an H100 (snowmiku, 238K Gaussians, 1000×750; ``profile_train_step``):
        the forward 3.26 → 2.65 ms; the backward, whose per-entry gradients are then
        reduced across threads, no faster (loss gradient 11.81 vs 11.73 ms at chunk 8,
        11.51 vs 11.54 ms at 16).
    interpret: run the kernels in Pallas' interpreter (any backend; for tests).

    The figures above were measured before the kernels' running transmittances became running
    products (``kernels.running_product``; the worlds' forward at chunks of 8 went from 128
    registers a thread to 80) and were not re-measured, except for the worlds' changed tiles at
    640×480, still read from a strip of rows: there chunks of 16 with read-ahead were 2 % faster
    than 8 (``phirie_jax.interact.batched.WORLD_RASTER``; 115 registers a thread, and 120 in
    ``composite_two_sets``), 8 warps 8–10 % slower.
    """

    chunk: int = 8
    backward_chunk: int = 8
    num_warps: int = 4
    backward_num_warps: int = 4
    prefetch: bool = False
    forward_entries_major: bool = True
    backward_entries_major: bool = False
    interpret: bool = False

    def __post_init__(self):
        for name in ("chunk", "backward_chunk", "num_warps", "backward_num_warps"):
            value = getattr(self, name)
            if value < 1 or value & (value - 1):
                raise ValueError(f"PallasSettings.{name}: {value} (expected a power of two)")


def _pixel_centres(grid: TileGrid, tile, dtype: jnp.dtype):
    """Pixel centres of tile ``tile`` () int32: x (P,), y (P,) and inside (P,) bool."""
    ts = grid.tile_size
    local = jnp.arange(grid.tile_pixels, dtype=jnp.int32)
    px = (tile % grid.tiles_x) * ts + local % ts
    py = (tile // grid.tiles_x) * ts + local // ts
    inside = (px < grid.width) & (py < grid.height)
    return px.astype(dtype) + 0.5, py.astype(dtype) + 0.5, inside


def _load_ids(ids_ref, start, end, first, chunk: int):
    """Entries [first, first + B) of a tile's list that starts at ``start`` () and whose
    entries in [0, end) are wanted (end (), first () int32); ids_ref (C,) ref.

    Returns pos (B,) int32 list positions, valid (B,) bool and ids (B,) int32 (0 where not
    valid).
    """
    pos = first + jnp.arange(chunk, dtype=jnp.int32)
    valid = (pos >= 0) & (pos < end)
    slot = jnp.clip(start + pos, 0, ids_ref.shape[0] - 1)
    return pos, valid, plgpu.load(ids_ref.at[slot], mask=valid, other=0)


def _load_rows(params_ref, ids, valid):
    """The D parameter columns of entries ids (B,) int32, each (B,) (0 where valid (B,) is
    false); params_ref (N, D) ref."""
    return [plgpu.load(params_ref.at[ids, k], mask=valid, other=0.0)
            for k in range(params_ref.shape[1])]


def _load_rows_of_two(first_ref, second_ref, ids, valid):
    """As ``_load_rows`` from the rows of two sets one after the other, without joining them:
    ids (B,) int32 < N₁ are rows of first_ref (N₁, D), the others rows of second_ref (N₂, D)
    from N₁ on; valid (B,) bool. Each entry reads only its own set's row (the other load is
    masked off)."""
    n1, n2 = first_ref.shape[0], second_ref.shape[0]
    in_first = ids < n1
    first_ids, second_ids = jnp.minimum(ids, n1 - 1), jnp.clip(ids - n1, 0, n2 - 1)
    return [jnp.where(in_first,
                      plgpu.load(first_ref.at[first_ids, k], mask=valid & in_first, other=0.0),
                      plgpu.load(second_ref.at[second_ids, k], mask=valid & ~in_first, other=0.0))
            for k in range(first_ref.shape[1])]


class _Chunks:
    """A tile's chunks in a given order, read ahead when ``prefetch`` is on.

    ``first(j)`` () int32 is the list position of the j-th chunk walked. The state carried
    through the loop holds the current chunk (pos, valid, ids, rows) and, with prefetching,
    the next chunk's (pos, valid, ids): its rows are gathered while the current chunk is
    composited, and the ids after it are read.
    """

    def __init__(self, ids_ref, load_rows: Callable, start, end, chunk: int, first: Callable,
                 prefetch: bool):
        """ids_ref (C,) ref; load_rows(ids (B,), valid (B,)) → the D parameter columns, each (B,)
        (``_load_rows``); start () and end () int32 as in ``_load_ids``."""
        self.ids_ref, self.load_rows = ids_ref, load_rows
        self.start, self.end, self.chunk = start, end, chunk
        self.first, self.prefetch = first, prefetch

    def _ids(self, j):
        """pos, valid, ids of the j-th chunk walked (j () int32)."""
        return _load_ids(self.ids_ref, self.start, self.end, self.first(j), self.chunk)

    def initial(self) -> tuple:
        """The loop state before the first chunk."""
        pos, valid, ids = self._ids(0)
        current = (pos, valid, ids, self.load_rows(ids, valid))
        return (current, self._ids(1)) if self.prefetch else (current,)

    def take(self, j, state: tuple):
        """The j-th chunk (j () int32): (pos, valid, ids, rows) and the state for step j + 1."""
        if not self.prefetch:
            pos, valid, ids = self._ids(j)
            current = (pos, valid, ids, self.load_rows(ids, valid))
            return current, state
        current, (pos, valid, ids) = state
        following = (pos, valid, ids, self.load_rows(ids, valid))
        return current, (following, self._ids(j + 2))


class _Block:
    """How a chunk's (entry, pixel) block is laid out: (P, B) pixels-major or (B, P)
    entries-major (``PallasSettings``). ``pix``/``ent`` broadcast a per-pixel
    (P,) or per-entry (B,) vector to the block; reductions name the axis they remove."""

    def __init__(self, entries_major: bool):
        self.entry_axis, self.pixel_axis = (0, 1) if entries_major else (1, 0)

    def pix(self, v):
        """v (P,) → (1, P) or (P, 1): broadcastable to the block."""
        return v[None, :] if self.entry_axis == 0 else v[:, None]

    def ent(self, v):
        """v (B,) → (B, 1) or (1, B): broadcastable to the block."""
        return v[:, None] if self.entry_axis == 0 else v[None, :]

    def over_entries(self, reduce: Callable, x):
        """The block x (B, P) or (P, B) reduced along its entries → (P,)."""
        return reduce(x, axis=self.entry_axis)

    def over_pixels(self, reduce: Callable, x):
        """The block x (B, P) or (P, B) reduced along its pixels → (B,)."""
        return reduce(x, axis=self.pixel_axis)

    def running(self, x):
        """x (B, P) or (P, B) → its inclusive cumulative sum along the entries (front to back)."""
        return jnp.cumsum(x, axis=self.entry_axis)

    def running_products(self, x):
        """x (B, P) or (P, B) → (before, upto): the products of the entries in front of each
        entry, and up to it (``kernels.running_product``)."""
        return running_products(x, self.entry_axis)


def _chunk_alpha(block: _Block, px, py, columns: list, valid):
    """α of B entries at P pixels: px (P,), py (P,), columns: D arrays (B,), valid (B,) →
    alpha (0 where skipped), raw o·G, dx, dy, each a block (``_Block``)."""
    pix, ent = block.pix, block.ent
    mx, my, a, b, c, opacity = columns[:NUM_GEOMETRY]
    dx = pix(px) - ent(mx)
    dy = pix(py) - ent(my)
    # σ·log2(e), its per-entry factors scaled before the block: e^σ = 2^(σ·log2 e)
    half_a, half_c, scaled_b = (-0.5 * LOG2_E) * a, (-0.5 * LOG2_E) * c, -LOG2_E * b
    sigma2 = ent(half_a) * dx * dx + ent(half_c) * dy * dy + ent(scaled_b) * dx * dy
    raw = ent(opacity) * jnp.exp2(sigma2)
    alpha = jnp.minimum(raw, ALPHA_MAX)
    alpha = jnp.where(ent(valid) & (alpha >= ALPHA_MIN), alpha, 0.0)
    return alpha, raw, dx, dy


def _forward_kernel(grid: TileGrid, settings: PallasSettings, with_last: bool, start_ref, count_ref,
                    ids_ref, params_ref, acc_ref, trans_ref, walked_ref, last_ref=None):
    """One tile, front to back.  start_ref (NT,) int32; count_ref (NT,) int32; ids_ref (C,) int32;
    params_ref (N, D); out: acc_ref (NT, CH, P), trans_ref (NT, P), walked_ref (NT,) int32
    (chunks walked) and, when ``with_last``, last_ref (NT, P) int32 (1 + list position of each
    pixel's last contributor, 0 if none: what the backward needs, left out of a render that is
    not differentiated)."""
    tile = pl.program_id(0)
    _walk_front_to_back(settings, with_last, _pixel_centres(grid, tile, params_ref.dtype),
                        start_ref[tile], count_ref[tile], ids_ref, partial(_load_rows, params_ref),
                        params_ref.shape[1], tile, acc_ref, trans_ref, walked_ref, last_ref)


def _two_sets_forward_kernel(image: TileGrid, settings: PallasSettings, start_ref, count_ref, ids_ref,
                             tiles_ref, first_ref, second_ref, acc_ref, trans_ref, walked_ref):
    """List k front to back over the pixels of image tile tiles_ref[k], its rows read from two
    sets (``_load_rows_of_two``: first_ref (N₁, D), second_ref (N₂, D)). start_ref (T,) int32;
    count_ref (T,) int32; ids_ref (C,) int32; tiles_ref (T,) int32; out: acc_ref (T, CH, P),
    trans_ref (T, P), walked_ref (T,) int32, as ``_forward_kernel``'s per list."""
    k = pl.program_id(0)
    _walk_front_to_back(settings, False, _pixel_centres(image, tiles_ref[k], first_ref.dtype),
                        start_ref[k], count_ref[k], ids_ref, partial(_load_rows_of_two, first_ref, second_ref),
                        first_ref.shape[1], k, acc_ref, trans_ref, walked_ref, None)


def _walk_front_to_back(settings: PallasSettings, with_last: bool, pixels: tuple, start, count, ids_ref,
                        load_rows: Callable, num_columns: int, out, acc_ref, trans_ref, walked_ref, last_ref):
    """Composite one list front to back and write row out () int32 of the outputs acc_ref
    (R, CH, P), trans_ref (R, P), walked_ref (R,) int32 and, with ``with_last``, last_ref
    (R, P) int32 (``_forward_kernel``). pixels: (px (P,), py (P,), inside (P,) bool)
    (``_pixel_centres``); the list's entries start () to start + count () of ids_ref (C,)
    int32, their D = num_columns parameter columns from load_rows (``_Chunks``)."""
    chunk, block = settings.chunk, _Block(settings.forward_entries_major)
    pix, ent = block.pix, block.ent
    channels = num_columns - NUM_GEOMETRY
    px, py, inside = pixels
    dtype = px.dtype
    npix = px.shape[0]
    n_chunks = (count + chunk - 1) // chunk
    chunks = _Chunks(ids_ref, load_rows, start, count, chunk, lambda i: i * chunk, settings.prefetch)

    def cond(carry):
        i, _, done, _, _, _ = carry
        return (i < n_chunks) & (jnp.min(done.astype(jnp.int32)) == 0)

    def body(carry):
        i, trans, done, last, acc, loads = carry
        (pos, valid, _, columns), loads = chunks.take(i, loads)
        alpha, _, _, _ = _chunk_alpha(block, px, py, columns, valid)
        keep = 1.0 - alpha                                # ≥ 0.01
        before, upto = block.running_products(keep)
        excl = pix(trans) * before                        # T before each entry, no stop
        incl = pix(trans) * upto                          # ... and after it
        # T only decreases: once an entry fails the floor every later one does too, so
        # ``active`` is exactly what the sequential 3DGS loop would add.
        active = pix(~done) & (alpha > 0.0) & (incl >= T_MIN)
        weights = jnp.where(active, alpha * excl, 0.0)
        acc = tuple(a + block.over_entries(jnp.sum, weights * ent(f))
                    for a, f in zip(acc, columns[NUM_GEOMETRY:]))
        done = done | (trans * block.over_entries(jnp.min, upto) < T_MIN)  # Π(1 − α): the last, the least
        trans = block.over_entries(jnp.min, jnp.where(active, incl, pix(trans)))
        if with_last:
            last = jnp.maximum(last, block.over_entries(jnp.max, jnp.where(active, ent(pos) + 1, 0)))
        return i + 1, trans, done, last, acc, loads

    # without ``with_last`` the carried ``last`` is a placeholder scalar that is never updated
    last0 = jnp.zeros((npix,), jnp.int32) if with_last else jnp.int32(0)
    carry = (jnp.int32(0), jnp.ones((npix,), dtype), ~inside, last0,
             tuple(jnp.zeros((npix,), dtype) for _ in range(channels)), chunks.initial())
    walked, trans, _, last, acc, _ = jax.lax.while_loop(cond, body, carry)
    for k in range(channels):
        acc_ref[out, k, :] = acc[k]
    trans_ref[out, :] = trans
    walked_ref[out] = walked
    if with_last:
        last_ref[out, :] = last


def _backward_kernel(grid: TileGrid, settings: PallasSettings, start_ref, ids_ref, params_ref,
                     trans_ref, last_ref, g_acc_ref, g_trans_ref, zeros_ref, grads_ref):
    """One tile, back to front.  start_ref (NT,) int32; ids_ref (C,) int32; params_ref (N, D);
    trans_ref (NT, P) final T; last_ref (NT, P) int32; g_acc_ref (NT, CH, P) and g_trans_ref
    (NT, P) output cotangents; zeros_ref (N + 1, D) aliased to grads_ref (N + 1, D), into which
    each entry's gradient is added (row N takes the adds of padding entries)."""
    del zeros_ref  # the same buffer as grads_ref
    tile = pl.program_id(0)
    chunk, block = settings.backward_chunk, _Block(settings.backward_entries_major)
    pix, ent = block.pix, block.ent
    num_columns = params_ref.shape[1]
    channels = num_columns - NUM_GEOMETRY
    dummy = params_ref.shape[0]
    start = start_ref[tile]
    px, py, _ = _pixel_centres(grid, tile, params_ref.dtype)
    trans_final = trans_ref[tile, :]
    last = last_ref[tile, :]
    g_acc = [g_acc_ref[tile, k, :] for k in range(channels)]
    end = jnp.max(last)  # entries after every pixel's last contributor changed nothing
    n_chunks = (end + chunk - 1) // chunk
    chunks = _Chunks(ids_ref, partial(_load_rows, params_ref), start, end, chunk,
                     lambda j: (n_chunks - 1 - j) * chunk, settings.prefetch)

    def body(j, carry):
        trans_after, rg_after, loads = carry  # rg: g·(everything behind this chunk), T·g_T included
        (pos, valid, ids, columns), loads = chunks.take(j, loads)
        alpha, raw, dx, dy = _chunk_alpha(block, px, py, columns, valid)
        active = (alpha > 0.0) & (ent(pos) < pix(last))
        alpha = jnp.where(active, alpha, 0.0)
        keep = 1.0 - alpha
        before, upto = block.running_products(keep)
        # T before the chunk = T after / Π(1 − α) (3DGS's division, once a pixel and chunk).
        trans_before = trans_after / block.over_entries(jnp.min, upto)
        t_excl = pix(trans_before) * before
        weights = alpha * t_excl
        features = columns[NUM_GEOMETRY:]
        g_feat = pix(g_acc[0]) * ent(features[0])
        for g, f in zip(g_acc[1:], features[1:]):
            g_feat = g_feat + pix(g) * ent(f)                 # g · f_j
        contrib = weights * g_feat
        contrib_total = block.over_entries(jnp.sum, contrib)
        behind = pix(rg_after + contrib_total) - block.running(contrib)  # Σ_{k > j}
        d_alpha = jnp.where(active, t_excl * g_feat - behind / keep, 0.0)
        d_raw = jnp.where(raw < ALPHA_MAX, d_alpha, 0.0)     # the clamp has zero slope
        d_sigma = d_raw * raw                                # d(o·e^σ)/dσ = o·e^σ
        total = partial(block.over_pixels, jnp.sum)
        # σ = −(a dx² + c dy²)/2 − b dx dy with dx = px − μx: the per-entry factors a, b, c
        # (and 1/o) are applied after the sums over the pixels, not to every pixel.
        s_x, s_y = total(d_sigma * dx), total(d_sigma * dy)
        a, b, c, opacity = columns[2:NUM_GEOMETRY]
        grads = [
            a * s_x + b * s_y,                               # ∂σ/∂μx = a dx + b dy
            b * s_x + c * s_y,
            -0.5 * total(d_sigma * dx * dx),
            -total(d_sigma * dx * dy),
            -0.5 * total(d_sigma * dy * dy),
            # ∂α/∂o = G, and d_raw·G = d_sigma / o (o = 0 has no active pixel: d_sigma = 0)
            jnp.where(opacity > 0.0, total(d_sigma) / jnp.where(opacity > 0.0, opacity, 1.0), 0.0),
        ] + [total(weights * pix(g)) for g in g_acc]         # ∂/∂f_j = w_j g
        rows = jnp.where(valid, ids, dummy)
        for k, grad in enumerate(grads):
            # The interpreter has no masked atomics; padding entries add 0 to row N anyway.
            plgpu.atomic_add(grads_ref, (rows, k), grad, mask=None if settings.interpret else valid)
        return trans_before, rg_after + contrib_total, loads

    jax.lax.fori_loop(0, n_chunks, body, (trans_final, trans_final * g_trans_ref[tile, :],
                                          chunks.initial()))


def _compiler_params(settings: PallasSettings, num_warps: int):
    """Triton's launch settings for a kernel of ``num_warps`` warps (none when interpreted)."""
    return None if settings.interpret else plgpu.CompilerParams(num_warps=num_warps)


def composite_pallas_forward(grid: TileGrid, settings: PallasSettings, params, lists: TileLists,
                             with_last: bool = True):
    """Forward pass over every tile.  params (N, D) → acc (NT, P, CH), T (NT, P), walked (NT,)
    int32 (chunks each tile walked) and last (NT, P) int32 (1 + list position of the last
    contributor, 0 if none; None unless ``with_last``: only the backward needs it)."""
    nt, npix = grid.num_tiles, grid.tile_pixels
    channels = params.shape[1] - NUM_GEOMETRY
    out_shape = [jax.ShapeDtypeStruct((nt, channels, npix), params.dtype),
                 jax.ShapeDtypeStruct((nt, npix), params.dtype),
                 jax.ShapeDtypeStruct((nt,), jnp.int32)]
    if with_last:
        out_shape.append(jax.ShapeDtypeStruct((nt, npix), jnp.int32))
    acc, trans, walked, *last = pl.pallas_call(
        partial(_forward_kernel, grid, settings, with_last),
        out_shape=tuple(out_shape),
        grid=(nt,),
        interpret=settings.interpret,
        compiler_params=_compiler_params(settings, settings.num_warps),
        name="composite_forward",
    )(lists.tile_start, lists.tile_count, lists.gaussian_ids, params)
    return jnp.swapaxes(acc, 1, 2), trans, walked, (last[0] if with_last else None)


@partial(jax.custom_vjp, nondiff_argnums=(0, 1))
def composite_two_sets(image: TileGrid, settings: PallasSettings, first_params, second_params,
                       lists: TileLists, tiles):
    """The forward over T lists, list k over the pixels of image tile tiles[k] (tiles (T,)
    int32), its entries' rows read from two sets without joining them (ids < N₁: rows of
    first_params (N₁, D), the others rows of second_params (N₂, D) from N₁ on): what
    ``composite_pallas_forward`` gives for the joined rows, list k's pixels those of image
    tile tiles[k]. lists: ``TileLists`` over the joined ids, gaussian_ids (C,), tile_start (T,)
    and tile_count (T,) int32.

    For many worlds over one static set: the static rows are read where they lie (shared by
    every world; under vmap they may stay unbatched), and no per-list copy of the rows is made.
    Returns acc (T, P, CH), transmittance (T, P) and walked (T,) int32. Not differentiable
    (``composite_pallas`` is)."""
    t, npix = tiles.shape[0], image.tile_pixels
    channels = first_params.shape[1] - NUM_GEOMETRY
    dtype = first_params.dtype
    acc, trans, walked = pl.pallas_call(
        partial(_two_sets_forward_kernel, image, settings),
        out_shape=(jax.ShapeDtypeStruct((t, channels, npix), dtype),
                   jax.ShapeDtypeStruct((t, npix), dtype),
                   jax.ShapeDtypeStruct((t,), jnp.int32)),
        grid=(t,),
        interpret=settings.interpret,
        compiler_params=_compiler_params(settings, settings.num_warps),
        name="composite_forward_two_sets",
    )(lists.tile_start, lists.tile_count, lists.gaussian_ids, tiles, first_params,
      second_params.astype(dtype))
    return jnp.swapaxes(acc, 1, 2), trans, walked


def _composite_two_sets_fwd(image: TileGrid, settings: PallasSettings, first_params, second_params,
                            lists: TileLists, tiles):
    """The primal and no residual: first_params (N₁, D), second_params (N₂, D), tiles (T,) int32."""
    return composite_two_sets(image, settings, first_params, second_params, lists, tiles), None


def _composite_two_sets_bwd(image: TileGrid, settings: PallasSettings, residuals: None, cotangents: tuple):
    """No backward: differentiating a render through ``composite_two_sets`` is refused
    (cotangents: acc (T, P, CH), transmittance (T, P), walked (T,))."""
    raise NotImplementedError("composite_two_sets has no backward: differentiate through "
                              "composite_pallas (e.g. kernels.raster_merge.rasterize_over_static)")


composite_two_sets.defvjp(_composite_two_sets_fwd, _composite_two_sets_bwd)


def composite_pallas_backward(grid: TileGrid, settings: PallasSettings, params, lists: TileLists,
                              trans, last, g_acc, g_trans):
    """d params (N, D) from output cotangents g_acc (NT, P, CH), g_trans (NT, P), given the
    forward's params (N, D), trans (NT, P) final transmittance and last (NT, P) int32."""
    n, d = params.shape
    grads = pl.pallas_call(
        partial(_backward_kernel, grid, settings),
        out_shape=jax.ShapeDtypeStruct((n + 1, d), params.dtype),
        grid=(grid.num_tiles,),
        input_output_aliases={7: 0},
        interpret=settings.interpret,
        compiler_params=_compiler_params(settings, settings.backward_num_warps),
        name="composite_backward",
    )(lists.tile_start, lists.gaussian_ids, params, trans, last,
      jnp.swapaxes(g_acc, 1, 2).astype(params.dtype), g_trans.astype(params.dtype),
      jnp.zeros((n + 1, d), params.dtype))
    return grads[:n]


@partial(jax.custom_vjp, nondiff_argnums=(0, 1))
def composite_pallas(grid: TileGrid, settings: PallasSettings, params, gaussian_ids, tile_start,
                     tile_count):
    """acc (NT, P, CH), final transmittance T (NT, P) and chunk steps () int32 of the longest
    tile, with a custom recompute-based VJP (``kernels.composite.composite``'s contract).
    params (N, D) is differentiable; gaussian_ids (C,), tile_start (NT,), tile_count (NT,)
    int32 are bookkeeping. Rendered without differentiating, no tile tracks its pixels' last
    contributors (the backward's residual)."""
    acc, trans, walked, _ = composite_pallas_forward(
        grid, settings, params, TileLists(gaussian_ids, tile_start, tile_count), with_last=False)
    return acc, trans, jnp.max(walked)


def _composite_pallas_fwd(grid: TileGrid, settings: PallasSettings, params, gaussian_ids,
                          tile_start, tile_count):
    """Forward and residuals; params (N, D), gaussian_ids (C,), tile_start (NT,), tile_count (NT,)."""
    lists = TileLists(gaussian_ids, tile_start, tile_count)
    acc, trans, walked, last = composite_pallas_forward(grid, settings, params, lists)
    return (acc, trans, jnp.max(walked)), (params, lists, trans, last)


def _composite_pallas_bwd(grid: TileGrid, settings: PallasSettings, residuals: tuple,
                          cotangents: tuple):
    """VJP: residuals (params, lists, T, last), cotangents (g_acc, g_T, _)."""
    params, lists, trans, last = residuals
    g_acc, g_trans, _ = cotangents  # the step count is an integer: no cotangent
    d_params = composite_pallas_backward(grid, settings, params, lists, trans, last, g_acc,
                                         g_trans)
    return d_params, None, None, None


composite_pallas.defvjp(_composite_pallas_fwd, _composite_pallas_bwd)
