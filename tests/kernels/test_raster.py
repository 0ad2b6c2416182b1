"""The tile rasterizer against a slow per-pixel NumPy reference, finite differences and
its own properties (constant features, overflow reporting, batching)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kernels.gaussians import Gaussians
from kernels.raster import RasterConfig, intersections_needed, rasterize, render_batch
from kernels.sh import sh_basis

IMAGE_TOL = 1e-4          # per-pixel agreement with the float64 reference
IMAGE_FRACTION = 0.999    # of pixels that must agree (threshold flips: α = 1/255, T = 1e-4, 3σ)
SATURATED_T_RTOL = 1e-2   # T ≈ 1e-4 read back from float32 alpha = 1 − T
FD_STEP = 1e-6            # central differences in float64
FD_RTOL = 1e-5            # directional derivative vs central difference (relative)
GRAD_MODES_TOL = 2e-4     # custom VJP vs plain autodiff in float32 (relative to the max)
WIDTH, HEIGHT = 72, 50    # deliberately not multiples of the 16-pixel tile
TILE = 16
# Most test scenes have N_SCENE Gaussians of SH degree 3 and 3 feature channels, so the
# program compiled for DEFAULT is reused (compiling dominates this file's time).
N_SCENE = 240

# Jitted once: eager dispatch of the many small ops would dominate the test time.
render = jax.jit(rasterize, static_argnames=("width", "height", "config"))
render_many = jax.jit(render_batch, static_argnames=("width", "height", "config"))


# --- scenes ---------------------------------------------------------------------------


def camera(width=WIDTH, height=HEIGHT, dtype=np.float32):
    K = np.array([[70.0, 0.0, width / 2 - 1.3], [0.0, 72.0, height / 2 + 0.7], [0.0, 0.0, 1.0]])
    rot = Rotation.from_euler("xyz", [8.0, -12.0, 3.0], degrees=True).as_matrix()
    w2c = np.eye(4)
    w2c[:3, :3] = rot
    w2c[:3, 3] = [0.1, -0.05, 0.3]
    return K.astype(dtype), w2c.astype(dtype)


def random_scene(seed, n=N_SCENE, degree=3, dtype=np.float32, spread=1.2):
    """Gaussians in front of, straddling and behind the camera; some off-screen, some
    nearly transparent, a few large and opaque so pixels reach the T floor."""
    rng = np.random.default_rng(seed)
    K, w2c = camera(dtype=np.float64)
    cam = rng.uniform([-spread, -spread * 0.8, 0.6], [spread, spread * 0.8, 5.0], size=(n, 3))
    cam[: n // 12, 2] = rng.uniform(-1.0, 0.01, size=n // 12)  # behind / at the near plane
    cam[n // 12: n // 6, :2] *= 2.5                           # partly or fully off-screen
    big = slice(n - n // 8, n)
    cam[big, 0] = -np.abs(cam[big, 0])  # the big opaque ones on the left only
    rot, trans = w2c[:3, :3], w2c[:3, 3]
    means = (cam - trans) @ rot  # camera → world
    log_scales = rng.normal(-3.4, 0.6, size=(n, 3))
    log_scales[big] = rng.normal(-1.8, 0.3, size=(n // 8, 3))
    logits = rng.normal(1.5, 1.5, size=n)
    logits[big] = 6.0
    sh = rng.normal(0.0, 0.25, size=(n, (degree + 1) ** 2, 3))
    sh[:, 0] = rng.normal(0.0, 1.0, size=(n, 3))
    g = Gaussians(
        means=jnp.asarray(means, dtype),
        quats=jnp.asarray(rng.normal(size=(n, 4)) * 1.7, dtype),
        log_scales=jnp.asarray(log_scales, dtype),
        opacity_logits=jnp.asarray(logits, dtype),
        sh=jnp.asarray(sh, dtype),
    )
    # Two arbitrary channels and a constant one (which must composite to alpha).
    features = jnp.asarray(np.concatenate([rng.normal(size=(n, 2)), np.ones((n, 1))], 1), dtype)
    return g, features


# --- the slow reference -----------------------------------------------------------------


def reference_render(g: Gaussians, K, w2c, width, height, background, features,
                     near=0.01, tile=TILE):
    """Every Gaussian, every pixel, in per-pixel depth order, float64 NumPy.

    Same rules as 3DGS: EWA with the clamped Jacobian, +0.3 px² dilation, α = min(0.99, o G),
    skip α < 1/255, stop before T < 1e-4; a Gaussian reaches the tiles of the bounding box of
    its ellipse at k = min(3, √(2 ln(255 o))) standard deviations.
    """
    means = np.asarray(g.means, np.float64)
    quats = np.asarray(g.quats, np.float64)
    scales = np.exp(np.asarray(g.log_scales, np.float64))
    opac = 1.0 / (1.0 + np.exp(-np.asarray(g.opacity_logits, np.float64)))
    sh = np.asarray(g.sh, np.float64)
    feats = np.asarray(features, np.float64)
    K, w2c = np.asarray(K, np.float64), np.asarray(w2c, np.float64)
    rot, trans = w2c[:3, :3], w2c[:3, 3]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    center = -rot.T @ trans

    rows = []
    for i in range(len(means)):
        p = rot @ means[i] + trans
        if p[2] <= near or opac[i] < 1.0 / 255.0:
            rows.append(None)
            continue
        mx, my = 0.15 * width / fx, 0.15 * height / fy
        tx = np.clip(p[0] / p[2], -cx / fx - mx, (width - cx) / fx + mx)
        ty = np.clip(p[1] / p[2], -cy / fy - my, (height - cy) / fy + my)
        jac = K[:2, :2] @ np.array([[1 / p[2], 0, -tx / p[2]], [0, 1 / p[2], -ty / p[2]]])
        q = quats[i] / np.linalg.norm(quats[i])
        r3 = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
        cov3 = r3 @ np.diag(scales[i] ** 2) @ r3.T
        cov2 = jac @ rot @ cov3 @ rot.T @ jac.T + 0.3 * np.eye(2)
        k = min(3.0, np.sqrt(2.0 * np.log(max(255.0 * opac[i], 1.0))))
        half = k * np.sqrt(np.diag(cov2))
        uv = K[:2, :2] @ (p[:2] / p[2]) + K[:2, 2]
        d = means[i] - center
        color = np.maximum(sh_basis(d / np.linalg.norm(d), 3)[: sh.shape[1]] @ sh[i] + 0.5, 0.0)
        rect = np.floor(np.concatenate([uv - half, uv + half]) / tile)
        rows.append((p[2], uv, np.linalg.inv(cov2), color, rect))

    xs, ys = np.meshgrid(np.arange(width), np.arange(height))
    pix = np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], axis=1)
    ptile = np.stack([xs.ravel() // tile, ys.ravel() // tile], axis=1)
    npix = len(pix)
    T = np.ones(npix)
    done = np.zeros(npix, bool)
    rgb, depth, feat = np.zeros((npix, 3)), np.zeros(npix), np.zeros((npix, feats.shape[1]))
    order = sorted((r[0], i) for i, r in enumerate(rows) if r is not None)
    for _, i in order:
        z, uv, conic, color, rect = rows[i]
        in_rect = ((ptile[:, 0] >= rect[0]) & (ptile[:, 0] <= rect[2])
                   & (ptile[:, 1] >= rect[1]) & (ptile[:, 1] <= rect[3]))
        d = pix - uv
        power = -0.5 * np.einsum("pi,ij,pj->p", d, conic, d)
        alpha = np.minimum(0.99, opac[i] * np.exp(power))
        live = in_rect & ~done & (alpha >= 1.0 / 255.0)
        test_t = T * (1.0 - alpha)
        stop = live & (test_t < 1e-4)
        done |= stop
        add = live & ~stop
        w = np.where(add, alpha * T, 0.0)
        rgb += w[:, None] * color
        depth += w * z
        feat += w[:, None] * feats[i]
        T = np.where(add, test_t, T)
    shape = (height, width)
    return {
        "rgb": (rgb + T[:, None] * background).reshape(shape + (3,)),
        "depth": depth.reshape(shape),
        "alpha": (1.0 - T).reshape(shape),
        "features": feat.reshape(shape + (feats.shape[1],)),
        "saturated": done.reshape(shape),
    }


def agreement(ours, ref):
    err = np.abs(np.asarray(ours, np.float64) - ref)
    err = err.reshape(ref.shape[0], ref.shape[1], -1).max(axis=-1)
    return float(np.mean(err <= IMAGE_TOL))


DEFAULT = RasterConfig(capacity=1 << 14)
CONFIGS = {
    "default": DEFAULT,
    # Few slots (the queue refills often), small chunks, the GPU's fused chunk loop.
    "sequential_small_chunks_few_slots": RasterConfig(capacity=1 << 14, chunk=8, slots=3,
                                                      sequential=True),
    "autodiff_scan": RasterConfig(capacity=1 << 14, chunk=16, backward="autodiff",
                                  tile_capacity=1 << 10),
}


@pytest.fixture(scope="module")
def scene_and_reference():
    g, feats = random_scene(seed=3)
    K, w2c = camera()
    bg = np.array([0.2, 0.5, 0.9], np.float32)
    ref = reference_render(g, K, w2c, WIDTH, HEIGHT, bg, feats)
    return g, feats, K, w2c, bg, ref


@pytest.mark.parametrize("name", list(CONFIGS))
def test_matches_reference(scene_and_reference, name):
    g, feats, K, w2c, bg, ref = scene_and_reference
    # The scene exercises the stop rule, empty pixels and partial tiles.
    assert ref["saturated"].mean() > 0.01
    assert (ref["alpha"] < 0.01).mean() > 0.01
    out = render(
        g, K, w2c, width=WIDTH, height=HEIGHT, background=bg, features=feats,
        config=CONFIGS[name])
    assert not bool(out.overflow)
    for key in ("rgb", "depth", "alpha", "features"):
        frac = agreement(getattr(out, key), ref[key])
        assert frac >= IMAGE_FRACTION, (key, frac)
    # The stop rule, sharply: where the reference stopped, the final transmittance
    # (≥ 1e-4, ~1e-6 or less without the rule) agrees relatively.
    sat = ref["saturated"]
    np.testing.assert_allclose(1.0 - np.asarray(out.alpha, np.float64)[sat],
                               1.0 - ref["alpha"][sat], rtol=SATURATED_T_RTOL)


def test_constant_feature_composites_to_alpha(scene_and_reference):
    g, feats, K, w2c, bg, _ = scene_and_reference
    out = render(g, K, w2c, width=WIDTH, height=HEIGHT, background=bg, features=feats,
                 config=DEFAULT)
    np.testing.assert_allclose(out.features[..., 2], out.alpha, atol=1e-5)  # Σ w = 1 − T


def test_normalized_depth_of_a_fronto_parallel_layer():
    """Gaussians all at view depth 2 m: the normalized depth is 2 wherever alpha > 0."""
    g, feats = random_scene(seed=1)
    n = g.num
    K, _ = camera()
    rng = np.random.default_rng(0)
    means = np.concatenate([rng.uniform(-1.5, 1.5, (n, 2)), np.full((n, 1), 2.0)], axis=1)
    g = g.replace(means=jnp.asarray(means, jnp.float32),
                  log_scales=jnp.asarray(np.full((n, 3), -3.2, np.float32)),
                  opacity_logits=jnp.asarray(np.full(n, 0.5, np.float32)))
    out = render(g, K, np.eye(4, dtype=np.float32), width=WIDTH, height=HEIGHT,
                 background=np.zeros(3, np.float32), features=feats, config=DEFAULT)
    hit = np.asarray(out.alpha) > 1e-3
    assert hit.mean() > 0.3
    np.testing.assert_allclose(np.asarray(out.depth_normalized)[hit], 2.0, rtol=1e-5)


def test_overflow_is_reported(scene_and_reference):
    g, feats, K, w2c, bg, _ = scene_and_reference
    full = render(g, K, w2c, width=WIDTH, height=HEIGHT, background=bg, features=feats,
                  config=DEFAULT)
    needed = int(full.num_intersections)
    assert not bool(full.overflow) and 512 < needed <= DEFAULT.capacity
    small = render(g, K, w2c, width=WIDTH, height=HEIGHT, background=bg, features=feats,
                   config=RasterConfig(capacity=512))
    assert bool(small.overflow) and int(small.num_intersections) == needed
    # What did fit was rendered (the nearest Gaussians first), the rest is missing.
    assert float(jnp.mean(small.alpha)) < float(jnp.mean(full.alpha))
    # The count from the projection alone is the one rendering reports, whatever the buffer.
    assert int(intersections_needed(g, K, w2c, width=WIDTH, height=HEIGHT, config=DEFAULT)) == needed


# --- gradients -------------------------------------------------------------------------


def _loss_fn(K, w2c, width, height, config, weights):
    def loss(g, feats, bg):
        out = rasterize(g, K, w2c, width=width, height=height, background=bg, features=feats,
                        config=config)
        return (jnp.sum(weights["rgb"] * out.rgb) + jnp.sum(weights["depth"] * out.depth)
                + jnp.sum(weights["alpha"] * out.alpha)
                + jnp.sum(weights["features"] * out.features))
    return loss


def _weights(rng, width, height, f, dtype):
    return {
        "rgb": jnp.asarray(rng.normal(size=(height, width, 3)), dtype),
        "depth": jnp.asarray(rng.normal(size=(height, width)), dtype),
        "alpha": jnp.asarray(rng.normal(size=(height, width)), dtype),
        "features": jnp.asarray(rng.normal(size=(height, width, f)), dtype),
    }


@pytest.mark.parametrize("backward", ["custom", pytest.param("autodiff", marks=pytest.mark.slow)])
def test_gradients_match_finite_differences(x64, backward):
    width, height = 40, 30
    g, feats = random_scene(seed=11, n=24, degree=2, dtype=np.float64, spread=0.5)
    K, w2c = camera(width, height, dtype=np.float64)
    bg = jnp.asarray([0.3, 0.1, 0.6])
    rng = np.random.default_rng(1)
    cfg = RasterConfig(capacity=1 << 12, chunk=4, slots=2, backward=backward,
                       tile_capacity=256)
    # One program for values and gradients: the finite differences reuse it.
    value_and_grad = jax.jit(jax.value_and_grad(
        _loss_fn(K, w2c, width, height, cfg,
                 _weights(rng, width, height, feats.shape[1], jnp.float64)),
        argnums=(0, 1, 2)))
    grads = value_and_grad(g, feats, bg)[1]
    loss = lambda *args: value_and_grad(*args)[0]  # noqa: E731
    primals = {"means": g.means, "quats": g.quats, "log_scales": g.log_scales,
               "opacity_logits": g.opacity_logits, "sh": g.sh, "features": feats,
               "background": bg}
    analytic = {**{k: getattr(grads[0], k) for k in primals if hasattr(grads[0], k)},
                "features": grads[1], "background": grads[2]}

    def evaluate(name, value):
        if name == "features":
            return loss(g, value, bg)
        if name == "background":
            return loss(g, feats, value)
        return loss(g.replace(**{name: value}), feats, bg)

    for name, x in primals.items():
        direction = jnp.asarray(rng.normal(size=x.shape))
        fd = (evaluate(name, x + FD_STEP * direction)
              - evaluate(name, x - FD_STEP * direction)) / (2 * FD_STEP)
        ad = jnp.sum(analytic[name] * direction)
        assert abs(float(ad)) > 1e-3, name  # the group really influences the loss
        np.testing.assert_allclose(float(ad), float(fd), rtol=FD_RTOL, err_msg=name)


@pytest.mark.slow
def test_custom_vjp_equals_autodiff_float32(scene_and_reference):
    g, feats, K, w2c, bg, _ = scene_and_reference
    rng = np.random.default_rng(2)
    weights = _weights(rng, WIDTH, HEIGHT, feats.shape[1], jnp.float32)
    results = []
    for cfg in (RasterConfig(capacity=1 << 14, slots=4),
                RasterConfig(capacity=1 << 14, backward="autodiff", tile_capacity=1 << 10)):
        loss = _loss_fn(K, w2c, WIDTH, HEIGHT, cfg, weights)
        results.append(jax.jit(jax.grad(loss, argnums=(0, 1, 2)))(g, feats, bg))
    for a, b in zip(jax.tree.leaves(results[0]), jax.tree.leaves(results[1])):
        scale = float(jnp.max(jnp.abs(b)))
        assert scale > 0
        np.testing.assert_allclose(a, b, atol=GRAD_MODES_TOL * scale)


# --- batching --------------------------------------------------------------------------


def test_render_batch_pairs_sets_with_cameras():
    cfg = DEFAULT
    sets = [random_scene(seed=s) for s in (21, 22, 23)]
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *[s[0] for s in sets])
    feats = jnp.stack([s[1] for s in sets])
    K, w2c = map(jnp.asarray, camera())
    Ks = jnp.stack([K, K * jnp.array([[1.1], [1.1], [1.0]]), K])
    w2cs = jnp.stack([w2c, w2c, w2c.at[:3, 3].add(0.05)])
    bgs = jnp.asarray(np.random.default_rng(0).uniform(size=(3, 3)), jnp.float32)
    batch = render_many(stacked, Ks, w2cs, width=WIDTH, height=HEIGHT, background=bgs,
                         features=feats, config=cfg)
    assert batch.rgb.shape == (3, HEIGHT, WIDTH, 3)
    for b in range(3):
        single = render(sets[b][0], Ks[b], w2cs[b], width=WIDTH, height=HEIGHT,
                           background=bgs[b], features=sets[b][1], config=cfg)
        for key in ("rgb", "depth", "alpha", "features"):
            np.testing.assert_allclose(getattr(batch, key)[b], getattr(single, key), atol=1e-6)
        assert int(batch.num_intersections[b]) == int(single.num_intersections)


def test_colour_only_render_equals_the_full_one(scene_and_reference):
    """depth=False drops one composited channel: colour, alpha and features are the full
    render's (the same sums in the same order), depth is zeros. (Its gradients are checked
    where training uses it: tests/capture/test_train.py's screen gradients against autodiff.)"""
    g, feats, K, w2c, bg, _ = scene_and_reference
    full = render(g, K, w2c, width=WIDTH, height=HEIGHT, background=bg, features=feats, config=DEFAULT)
    colour = render(g, K, w2c, width=WIDTH, height=HEIGHT, background=bg, features=feats,
                    config=dataclasses.replace(DEFAULT, depth=False))
    for key in ("rgb", "alpha", "features"):
        np.testing.assert_allclose(getattr(colour, key), getattr(full, key), atol=1e-6, err_msg=key)
    assert float(jnp.max(jnp.abs(full.depth))) > 0 and not np.any(np.asarray(colour.depth))


def test_tile_reached_equals_checking_every_pixel_centre():
    """``tile_reached`` against α evaluated at each of the tile's pixel centres (float64)."""
    from kernels.project import ALPHA_MIN
    from kernels.raster import tile_reached

    rng = np.random.default_rng(4)
    m, tile = 4000, 16
    means = rng.uniform(-40, 72, size=(m, 2))
    sigma = np.exp(rng.uniform(np.log(0.5), np.log(30), size=(m, 2)))
    angle = rng.uniform(0, np.pi, m)
    rot = np.stack([np.stack([np.cos(angle), -np.sin(angle)], -1), np.stack([np.sin(angle), np.cos(angle)], -1)], -2)
    cov = rot @ (sigma[:, :, None] ** 2 * np.eye(2)) @ np.swapaxes(rot, 1, 2)
    inv = np.linalg.inv(cov)
    conics = np.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1)
    opacity = rng.uniform(0.002, 1.0, m)
    tx, ty = rng.integers(0, 2, m), rng.integers(0, 2, m)
    got = np.asarray(tile_reached(jnp.asarray(means, jnp.float32), jnp.asarray(conics, jnp.float32),
                                  jnp.asarray(opacity, jnp.float32), jnp.asarray(tx, jnp.int32),
                                  jnp.asarray(ty, jnp.int32), tile))
    local = np.arange(tile) + 0.5
    px = tx[:, None, None] * tile + local[None, None, :] - means[:, 0, None, None]
    py = ty[:, None, None] * tile + local[None, :, None] - means[:, 1, None, None]
    q = conics[:, 0, None, None] * px ** 2 + 2 * conics[:, 1, None, None] * px * py + conics[:, 2, None, None] * py ** 2
    alpha = opacity[:, None, None] * np.exp(-0.5 * q)
    want = (alpha >= ALPHA_MIN).any(axis=(1, 2))
    assert not np.any(want & ~got), "a tile the Gaussian reaches was dropped"
    near_limit = np.abs(q.min(axis=(1, 2)) - 2 * np.log(opacity / ALPHA_MIN)) < 1e-2
    assert np.array_equal(got[~near_limit], want[~near_limit])
    assert 0.2 < want.mean() < 0.8  # both answers are exercised


def test_the_pallas_compositor_is_refused_without_its_custom_backward():
    """Asked for explicitly with the autodiff backward, the Pallas compositor (which has only its
    custom backward) is refused where every path resolves the compositor; "auto" then picks JAX."""
    with pytest.raises(ValueError, match="only the custom backward"):
        RasterConfig(compositor="pallas", backward="autodiff").resolved_compositor()
    assert RasterConfig(backward="autodiff").resolved_compositor() == "jax"
