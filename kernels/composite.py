"""Front-to-back alpha compositing of per-tile, depth-sorted Gaussian lists.

The unit of work is one *chunk*: B consecutive entries of one tile's list against the
tile's T×T pixels, written for one tile and vmapped. Tiles are fed through a fixed
number of *slots* (a work queue inside ``lax.while_loop``): a slot keeps working on its
tile until every pixel is saturated or the list ends, then writes the tile out and
takes the next tile (longest lists first). So the work is bounded by what each tile
needs (early exit per tile), no tile waits for the slowest one, and every shape is
static. Idle slots still compute (masked), so a CPU wants few; a GPU wants enough to
fill it, but not so many that most of them idle while the longest tiles finish
(``kernels.raster.RasterConfig.resolved_slots``).

Rules (INRIA 3DGS): α = min(0.99, o·exp(−½ dᵀΣ⁻¹d)); α < 1/255 is skipped; a Gaussian
whose inclusion would bring the transmittance below 1e-4 is not added and the pixel
stops there. Outputs per pixel: Σ wᵢ fᵢ with wᵢ = αᵢ Tᵢ for every feature channel, and
the final transmittance T.

Gradients: ``composite`` has a custom VJP that recomputes α and walks each tile
back to front from its last contributor, recovering Tᵢ from the final transmittance
by division (Tᵢ = Tᵢ₊₁ / (1 − αᵢ), safe since α ≤ 0.99 and T ≥ 1e-4), as 3DGS does.
``composite_scan`` is the same forward as a fixed-length scan over all tiles, for
plain reverse-mode autodiff (kept for comparison and as a cross-check).

Parameter rows (N, D), D = 6 + CH: [μx, μy, a, b, c, opacity, features...] with
(a, b, c) the conic, i.e. Σ⁻¹ = [[a, b], [b, c]].
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp

from kernels.project import ALPHA_MIN
from kernels.pytree import pytree_dataclass

ALPHA_MAX = 0.99  # α clamp: keeps 1 − α ≥ 0.01 so the backward division is safe
T_MIN = 1e-4      # transmittance floor: the pixel is done before T would drop below it
NUM_GEOMETRY = 6  # leading parameter columns before the features


@dataclasses.dataclass(frozen=True)
class TileGrid:
    """Static image/tile layout (hashable: part of the compiled program's key)."""

    width: int
    height: int
    tile_size: int = 16

    @property
    def tiles_x(self) -> int:
        return -(-self.width // self.tile_size)

    @property
    def tiles_y(self) -> int:
        return -(-self.height // self.tile_size)

    @property
    def num_tiles(self) -> int:
        return self.tiles_x * self.tiles_y

    @property
    def tile_pixels(self) -> int:
        return self.tile_size * self.tile_size


@pytree_dataclass
class TileLists:
    """Tile–Gaussian intersections sorted by (tile, depth)."""

    gaussian_ids: jax.Array  # (C,) int32 Gaussian index of each sorted intersection
    tile_start: jax.Array    # (NT,) int32 first entry of each tile in gaussian_ids
    tile_count: jax.Array    # (NT,) int32 entries of each tile (what fitted in C)


def tile_pixels(grid: TileGrid, tile, dtype: jnp.dtype):
    """Pixel centres of one tile (tile () int32): (P, 2) (x, y) and (P,) bool inside the image."""
    ts = grid.tile_size
    ty, tx = tile // grid.tiles_x, tile % grid.tiles_x
    local = jnp.arange(grid.tile_pixels, dtype=jnp.int32)
    px = tx * ts + local % ts
    py = ty * ts + local // ts
    centres = jnp.stack([px, py], axis=-1).astype(dtype) + 0.5
    return centres, (px < grid.width) & (py < grid.height)


# --- one chunk of one tile --------------------------------------------------------------


def _chunk_alpha(pix, params, valid):
    """α of B Gaussians at P pixels.  pix (P, 2), params (B, D), valid (B,) →
    alpha (P, B) (0 where skipped), gauss (P, B), raw o·G (P, B), dx, dy (P, B)."""
    dx = pix[:, 0:1] - params[None, :, 0]
    dy = pix[:, 1:2] - params[None, :, 1]
    a, b, c, opacity = params[:, 2], params[:, 3], params[:, 4], params[:, 5]
    sigma = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
    gauss = jnp.exp(sigma)
    raw = opacity * gauss
    alpha = jnp.minimum(raw, ALPHA_MAX)
    alpha = jnp.where(valid[None, :] & (alpha >= ALPHA_MIN), alpha, 0.0)
    return alpha, gauss, raw, dx, dy


def _dot(a, b):
    """a (M, K) @ b (K, L) → (M, L) at full float32 precision."""
    # Full float32 accuracy: these sums are transmittances and colours, and a GPU would
    # otherwise be free to use TF32 (10-bit mantissa) for float32 products.
    return jnp.matmul(a, b, precision=jax.lax.Precision.HIGHEST)


def _triangle(size: int, dtype: jnp.dtype, *, strict: bool):
    """(B, B) M with M[k, j] = 1 where k ≤ j (k < j if strict): x @ M sums x over k ≤ j.

    Running products along a chunk are done as exp of such sums of log(1 − α): one small
    matrix product instead of a log-depth scan, which XLA runs much faster on CPU and GPU.
    """
    return jnp.triu(jnp.ones((size, size), dtype), k=1 if strict else 0)


def _forward_chunk(state: tuple, pix, params, valid, pos):
    """Composite one chunk into one tile's running state.

    state: T (P,), done (P,) bool, acc (P, CH), last (P,) int32 (1 + list position of the
    last contributor, 0 if none). pix (P, 2), params (B, D), valid (B,), pos (B,) int32.
    """
    trans, done, acc, last = state
    alpha, _, _, _, _ = _chunk_alpha(pix, params, valid)
    log_keep = jnp.log1p(-alpha)  # (P, B), ≥ log(0.01)
    incl = trans[:, None] * jnp.exp(_dot(log_keep, _triangle(alpha.shape[1], alpha.dtype,
                                                              strict=False)))
    # incl: T after each entry without stopping. T only decreases, so once an entry fails
    # the floor every later one does too: ``active`` is exactly the set that the
    # sequential 3DGS loop would add.
    active = (~done)[:, None] & (alpha > 0.0) & (incl >= T_MIN)
    excl = jnp.concatenate([trans[:, None], incl[:, :-1]], axis=1)
    weights = jnp.where(active, alpha * excl, 0.0)
    acc = acc + _dot(weights, params[:, NUM_GEOMETRY:])
    trans = jnp.min(jnp.where(active, incl, trans[:, None]), axis=1)
    done = done | (incl[:, -1] < T_MIN)
    last = jnp.maximum(last, jnp.max(jnp.where(active, pos[None, :] + 1, 0), axis=1))
    return trans, done, acc, last


def _forward_chunk_sequential(state: tuple, pix, params, valid, pos):
    """Same result as ``_forward_chunk``, as the literal 3DGS loop unrolled over the chunk.

    state as there; pix (P, 2), params (B, D), valid (B,) bool, pos (B,) int32.

    Every step is elementwise over the tile's pixels, so XLA can fuse the whole chunk
    into one kernel with no (P, B) intermediates in memory. On an H100 that was 3× faster
    for 2048 tiles in isolation, but inside the queue loop its speed swung with the slot
    count (from 0.8× to 7× the time of ``_forward_chunk``) and it compiled 5–15× slower;
    on a CPU it is no faster. Hence opt-in (``RasterConfig.sequential``).
    """
    trans, done, acc, last = state
    feats = params[:, NUM_GEOMETRY:]
    for j in range(params.shape[0]):
        p = params[j]
        dx = pix[:, 0] - p[0]
        dy = pix[:, 1] - p[1]
        sigma = -0.5 * (p[2] * dx * dx + p[4] * dy * dy) - p[3] * dx * dy
        alpha = jnp.minimum(p[5] * jnp.exp(sigma), ALPHA_MAX)
        alpha = jnp.where(valid[j] & (alpha >= ALPHA_MIN), alpha, 0.0)
        test = trans * (1.0 - alpha)
        live = (~done) & (alpha > 0.0)
        stop = live & (test < T_MIN)
        add = live & ~stop
        acc = acc + jnp.where(add, alpha * trans, 0.0)[:, None] * feats[j]
        trans = jnp.where(add, test, trans)
        done = done | stop
        last = jnp.where(add, pos[j] + 1, last)
    return trans, done, acc, last


def _backward_chunk(state: tuple, pix, params, valid, pos, last, g_acc):
    """One chunk of one tile, back to front.

    state: T after this chunk (P,), rg (P,) = g·(everything composited behind this chunk,
    T_final·g_T included). pix (P, 2), params (B, D), valid (B,) bool, pos (B,) int32;
    last (P,) int32, g_acc (P, CH) output cotangents.
    Returns the state before this chunk and d params (B, D).
    """
    trans_after, rg_after = state
    alpha, gauss, raw, dx, dy = _chunk_alpha(pix, params, valid)
    active = (alpha > 0.0) & (pos[None, :] < last[:, None])
    alpha = jnp.where(active, alpha, 0.0)
    one_minus = 1.0 - alpha
    log_keep = jnp.log1p(-alpha)
    size, dtype = alpha.shape[1], alpha.dtype
    # T before the chunk = T after / Π(1 − α) (3DGS's division, as one exp of a sum).
    trans_before = trans_after * jnp.exp(-jnp.sum(log_keep, axis=1))
    t_excl = trans_before[:, None] * jnp.exp(_dot(log_keep, _triangle(size, dtype, strict=True)))
    weights = alpha * t_excl
    feats = params[:, NUM_GEOMETRY:]
    g_feat = _dot(g_acc, feats.T)                       # (P, B): g · f_j
    contrib = weights * g_feat
    after_j = _dot(contrib, _triangle(size, dtype, strict=True).T)  # Σ_{k > j}
    behind = rg_after[:, None] + after_j                # + T_final g_T, in rg
    d_alpha = jnp.where(active, t_excl * g_feat - behind / one_minus, 0.0)
    d_raw = jnp.where(raw < ALPHA_MAX, d_alpha, 0.0)    # the clamp has zero slope
    a, b, c = params[:, 2], params[:, 3], params[:, 4]
    d_sigma = d_raw * raw                               # d(o·e^σ)/dσ = o·e^σ
    grads = jnp.concatenate([
        jnp.stack([
            jnp.sum(d_sigma * (a * dx + b * dy), axis=0),   # ∂σ/∂μx = a dx + b dy
            jnp.sum(d_sigma * (b * dx + c * dy), axis=0),
            jnp.sum(d_sigma * (-0.5 * dx * dx), axis=0),
            jnp.sum(d_sigma * (-dx * dy), axis=0),
            jnp.sum(d_sigma * (-0.5 * dy * dy), axis=0),
            jnp.sum(d_raw * gauss, axis=0),                 # ∂α/∂o = G
        ], axis=1),
        _dot(weights.T, g_acc),                             # ∂/∂f_j = w_j g
    ], axis=1)
    return (trans_before, rg_after + jnp.sum(contrib, axis=1)), grads


# --- the tile work queue -------------------------------------------------------------


def _gather_chunk(grid: TileGrid, chunk: int, params, lists: TileLists, tiles, chunk_index):
    """Rows of the chunk ``chunk_index`` (S,) int32 of each of S tiles: tiles (S,) int32 (NT = no
    tile); params (N, D).

    Returns ids (S, B), rows (S, B, D), valid (S, B), pos (S, B), pixel centres (S, P, 2).
    """
    nt = grid.num_tiles
    has = tiles < nt
    tile_c = jnp.minimum(tiles, nt - 1)
    start = lists.tile_start[tile_c]
    count = jnp.where(has, lists.tile_count[tile_c], 0)
    pos = chunk_index[:, None] * chunk + jnp.arange(chunk, dtype=jnp.int32)[None, :]
    valid = (pos >= 0) & (pos < count[:, None])
    cap = lists.gaussian_ids.shape[0]
    ids = lists.gaussian_ids[jnp.clip(start[:, None] + pos, 0, cap - 1)]
    pix, _ = jax.vmap(lambda t: tile_pixels(grid, t, params.dtype))(tile_c)
    return ids, params[ids], valid, pos, pix, count


def _refill(finished, tiles, queue, n_work, next_q):
    """Give each finished slot the next queued tile (NT when the queue is empty).

    finished (S,) bool; tiles (S,) int32; queue (NT,) int32; n_work () int32 tiles with work;
    next_q () int32 next queue position. → tiles (S,), next_q ().
    """
    nt = queue.shape[0]
    rank = jnp.cumsum(finished.astype(jnp.int32)) - 1
    qpos = next_q + rank
    fresh = jnp.where(qpos < n_work, queue[jnp.clip(qpos, 0, nt - 1)], nt)
    return jnp.where(finished, fresh, tiles), next_q + jnp.sum(finished, dtype=jnp.int32)


def _work_queue(work):
    """Tiles with work (work (NT,) int32), most work first: queue (NT,) int32, number with work ()."""
    queue = jnp.argsort(-work, stable=True).astype(jnp.int32)
    return queue, jnp.sum(work > 0, dtype=jnp.int32)


def _initial_slots(queue, n_work, slots: int):
    """The first tile of each slot: queue (NT,) int32, n_work () int32. → tiles (slots,), next_q ()."""
    q = jnp.arange(slots, dtype=jnp.int32)
    nt = queue.shape[0]
    tiles = jnp.where(q < n_work, queue[jnp.minimum(q, nt - 1)], nt)
    return tiles, jnp.minimum(n_work, slots)


def composite_forward(grid: TileGrid, slots: int, chunk: int, params, lists: TileLists,
                      sequential: bool = False):
    """Forward pass over every tile.  params (N, D) →
    acc (NT, P, CH), T (NT, P), last (NT, P) int32, steps () int32 (loop iterations).

    sequential: composite each chunk with ``_forward_chunk_sequential`` instead of
    ``_forward_chunk``; the results agree to float rounding.
    """
    chunk_fn = _forward_chunk_sequential if sequential else _forward_chunk
    nt, npix = grid.num_tiles, grid.tile_pixels
    ch = params.shape[1] - NUM_GEOMETRY
    dtype = params.dtype
    queue, n_work = _work_queue(lists.tile_count)
    tiles0, next0 = _initial_slots(queue, n_work, slots)

    def fresh_state(tiles):
        _, inside = jax.vmap(lambda t: tile_pixels(grid, t, dtype))(jnp.minimum(tiles, nt - 1))
        return (jnp.ones((slots, npix), dtype), ~inside,
                jnp.zeros((slots, npix, ch), dtype), jnp.zeros((slots, npix), jnp.int32))

    images = (jnp.zeros((nt, npix, ch), dtype), jnp.ones((nt, npix), dtype),
              jnp.zeros((nt, npix), jnp.int32))
    carry0 = (tiles0, jnp.zeros(slots, jnp.int32), fresh_state(tiles0), next0, images,
              jnp.zeros((), jnp.int32))

    def cond(carry):
        return jnp.any(carry[0] < nt)

    def body(carry):
        tiles, chunk_index, state, next_q, (acc_img, t_img, last_img), steps = carry
        _, rows, valid, pos, pix, count = _gather_chunk(grid, chunk, params, lists, tiles,
                                                        chunk_index)
        state = jax.vmap(chunk_fn)(state, pix, rows, valid, pos)
        chunk_index = chunk_index + 1
        trans, done, acc, last = state
        finished = (tiles < nt) & ((chunk_index * chunk >= count) | jnp.all(done, axis=1))
        out = jnp.where(finished, tiles, nt)  # nt is out of range: dropped
        acc_img = acc_img.at[out].set(acc, mode="drop")
        t_img = t_img.at[out].set(trans, mode="drop")
        last_img = last_img.at[out].set(last, mode="drop")
        tiles, next_q = _refill(finished, tiles, queue, n_work, next_q)
        fresh = fresh_state(tiles)
        state = jax.tree.map(
            lambda f, s: jnp.where(finished.reshape((-1,) + (1,) * (s.ndim - 1)), f, s),
            fresh, state)
        chunk_index = jnp.where(finished, 0, chunk_index)
        return tiles, chunk_index, state, next_q, (acc_img, t_img, last_img), steps + 1

    *_, images, steps = jax.lax.while_loop(cond, body, carry0)
    return (*images, steps)


def composite_backward(grid: TileGrid, slots: int, chunk: int, params, lists: TileLists,
                       t_img, last_img, g_acc, g_t):
    """d params (N, D) from output cotangents g_acc (NT, P, CH), g_t (NT, P), given the forward's
    params (N, D), t_img (NT, P) final transmittance and last_img (NT, P) int32 last contributors."""
    nt = grid.num_tiles
    n = params.shape[0]
    last_tile = jnp.max(last_img, axis=1)
    n_chunks = (last_tile + chunk - 1) // chunk  # chunks up to the tile's last contributor
    queue, n_work = _work_queue(n_chunks)
    tiles0, next0 = _initial_slots(queue, n_work, slots)

    def fresh_state(tiles):
        tile_c = jnp.minimum(tiles, nt - 1)
        trans = t_img[tile_c]
        return (trans, trans * g_t[tile_c]), n_chunks[tile_c] - 1

    state0, chunk0 = fresh_state(tiles0)
    carry0 = (tiles0, chunk0, state0, next0, jnp.zeros_like(params))

    def cond(carry):
        return jnp.any(carry[0] < nt)

    def body(carry):
        tiles, chunk_index, state, next_q, grads = carry
        ids, rows, valid, pos, pix, _ = _gather_chunk(grid, chunk, params, lists, tiles,
                                                      chunk_index)
        tile_c = jnp.minimum(tiles, nt - 1)
        state, d_rows = jax.vmap(_backward_chunk)(
            state, pix, rows, valid, pos, last_img[tile_c], g_acc[tile_c])
        grads = grads.at[jnp.where(valid, ids, n)].add(d_rows, mode="drop")
        finished = (tiles < nt) & (chunk_index <= 0)
        tiles, next_q = _refill(finished, tiles, queue, n_work, next_q)
        fresh, fresh_chunk = fresh_state(tiles)
        state = jax.tree.map(lambda f, s: jnp.where(finished[:, None], f, s), fresh, state)
        chunk_index = jnp.where(finished, fresh_chunk, chunk_index - 1)
        return tiles, chunk_index, state, next_q, grads

    return jax.lax.while_loop(cond, body, carry0)[-1]


@partial(jax.custom_vjp, nondiff_argnums=(0, 1, 2, 3))
def composite(grid: TileGrid, slots: int, chunk: int, sequential: bool, params, gaussian_ids,
              tile_start, tile_count):
    """acc (NT, P, CH), final transmittance T (NT, P) and loop steps () int32, with a
    custom recompute-based VJP. params (N, D) is differentiable; the int32 list arrays
    (``TileLists``: gaussian_ids (C,), tile_start (NT,), tile_count (NT,)) are bookkeeping.
    """
    acc, trans, _, steps = composite_forward(grid, slots, chunk, params,
                                             TileLists(gaussian_ids, tile_start, tile_count),
                                             sequential)
    return acc, trans, steps


def _composite_fwd(grid: TileGrid, slots: int, chunk: int, sequential: bool, params, gaussian_ids,
                   tile_start, tile_count):
    """``composite``'s forward and residuals; params (N, D), gaussian_ids (C,), tile_start (NT,),
    tile_count (NT,) as there."""
    lists = TileLists(gaussian_ids, tile_start, tile_count)
    acc, trans, last, steps = composite_forward(grid, slots, chunk, params, lists, sequential)
    return (acc, trans, steps), (params, lists, trans, last)


def _composite_bwd(grid: TileGrid, slots: int, chunk: int, sequential: bool, residuals: tuple,
                   cotangents: tuple):
    """``composite``'s VJP: residuals (params, lists, T, last), cotangents (g_acc, g_t, _)."""
    params, lists, trans, last = residuals
    g_acc, g_t, _ = cotangents  # the step count is an integer: no cotangent
    d_params = composite_backward(grid, slots, chunk, params, lists, trans, last, g_acc, g_t)
    return d_params, None, None, None


composite.defvjp(_composite_fwd, _composite_bwd)


def composite_scan(grid: TileGrid, chunk: int, max_chunks: int, params, lists: TileLists):
    """The same forward for plain autodiff: every tile, ``max_chunks`` chunks, no early exit.
    params (N, D).

    Entries past ``max_chunks · chunk`` in a tile are not composited: the caller must
    check the longest tile list against that (``RasterConfig.tile_capacity``).
    Returns acc (NT, P, CH), T (NT, P).
    """
    nt, npix = grid.num_tiles, grid.tile_pixels
    ch = params.shape[1] - NUM_GEOMETRY
    tiles = jnp.arange(nt, dtype=jnp.int32)
    _, inside = jax.vmap(lambda t: tile_pixels(grid, t, params.dtype))(tiles)
    state0 = (jnp.ones((nt, npix), params.dtype), ~inside,
              jnp.zeros((nt, npix, ch), params.dtype), jnp.zeros((nt, npix), jnp.int32))

    @jax.checkpoint  # keep only the carry per step; recompute the chunk in the backward
    def step(state, c):
        _, rows, valid, pos, pix, _ = _gather_chunk(
            grid, chunk, params, lists, tiles, jnp.full((nt,), c, jnp.int32))
        return jax.vmap(_forward_chunk)(state, pix, rows, valid, pos), None

    (trans, _, acc, _), _ = jax.lax.scan(step, state0, jnp.arange(max_chunks, dtype=jnp.int32))
    return acc, trans
