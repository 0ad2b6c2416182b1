"""The plane-disk fill kernel: gradients reach only the new disks, the layered composition is the
renderer's, and a hole of known colour in a plane is recovered by the fit."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kernels import fill
from kernels.gaussians import Gaussians
from kernels.raster import RasterConfig, rasterize
from kernels.sh import SH_C0

C = 32                    # crop size (two tiles)
FOCAL = 150.0             # px: the 6 cm hole spans 18 px from 0.5 m
GRID = 0.01               # disk spacing, m
KEPT_SPACING = 0.008
GREY, RED = np.array([0.5, 0.5, 0.5]), np.array([0.9, 0.15, 0.1])
BACKGROUND = np.array([0.1, 0.2, 0.3], np.float32)
HOLE = 0.03               # half side of the square hole, m (the crop sees ±5.3 cm)
CONFIG = RasterConfig(capacity=1 << 15)
DSSIM = 0.2
COMPOSE_TOL = 1e-5        # layered composition vs one render
RECOVER_TOL = 0.06        # mean |rendered − red| inside the hole after the fit
STEPS = 80
EDGE_PX = 5               # the kept disks' 2σ at the rim of the hole, px


def camera():
    K = np.array([[FOCAL, 0, C / 2], [0, FOCAL, C / 2], [0, 0, 1]], np.float32)
    w2c = np.eye(4, dtype=np.float32)  # looking down −z from 0.5 m: x right, y down
    w2c[:3, :3] = np.diag([1.0, -1.0, -1.0])
    w2c[2, 3] = 0.5
    return jnp.asarray(K), jnp.asarray(w2c)


def flat(points, colour, sigma, opacity=0.95):
    n = len(points)
    return Gaussians(
        means=jnp.asarray(points, jnp.float32), quats=jnp.tile(jnp.array([1.0, 0, 0, 0]), (n, 1)),
        log_scales=jnp.log(jnp.tile(jnp.array([sigma, sigma, 0.1 * sigma], jnp.float32), (n, 1))),
        opacity_logits=jnp.full((n,), np.log(opacity / (1 - opacity)), jnp.float32),
        sh=jnp.asarray(np.tile((colour - 0.5) / SH_C0, (n, 1, 1)), jnp.float32))


def lattice(spacing, half):
    xs = np.arange(-half, half + 1e-9, spacing)
    xy = np.stack(np.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
    return np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)


@pytest.fixture(scope="module")
def scene():
    """A grey plane with a square hole, new disks over the hole (+ one cell), padding, one disk
    the frame does not list, and a target that is red in the hole."""
    kept_pts = lattice(KEPT_SPACING, 0.09)
    kept_pts = kept_pts[np.max(np.abs(kept_pts[:, :2]), axis=1) > HOLE]
    slab = flat(kept_pts, GREY, 0.9 * KEPT_SPACING)
    disk_pts = lattice(GRID, HOLE + GRID)
    n, size = len(disk_pts), 128
    assert n < size - 1
    centres = np.zeros((size, 3), np.float32)
    centres[:n] = disk_pts
    centres[n] = [0.05, 0.05, 0.0]  # a real disk that the frame does not list
    tangents = np.tile(np.eye(3, dtype=np.float32)[None, :2], (size, 1, 1))
    geom = fill.FillGeometry(
        centres=jnp.asarray(centres), tangents=jnp.asarray(tangents), quats=jnp.tile(jnp.array([1.0, 0, 0, 0]), (size, 1)),
        log_thickness=jnp.full((size,), np.log(0.1 * 0.9 * GRID), jnp.float32),
        valid=jnp.asarray(np.arange(size) <= n), max_offset=jnp.float32(GRID),
        min_log_scale=jnp.float32(np.log(0.25 * GRID)), max_log_scale=jnp.float32(np.log(1.5 * GRID)))
    params = fill.FillParams(
        dc=jnp.asarray(np.tile((GREY - 0.5) / SH_C0, (size, 1)), jnp.float32),
        opacity_logits=jnp.full((size,), 2.0, jnp.float32), raw_offsets=jnp.zeros((size, 2), jnp.float32),
        log_scales=jnp.full((size, 2), np.log(0.9 * GRID), jnp.float32))
    K, w2c = camera()
    kept = render(slab, K, w2c, width=C, height=C, background=BACKGROUND, config=CONFIG)
    uv = (np.asarray(K) @ (np.asarray(w2c)[:3, :3] @ np.array([[-HOLE, -HOLE, 0], [HOLE, HOLE, 0]]).T
                            + np.asarray(w2c)[:3, 3:])).T
    uv = uv[:, :2] / uv[:, 2:]
    (x0, y0), (x1, y1) = np.floor(uv.min(0)).astype(int), np.ceil(uv.max(0)).astype(int)
    target = np.asarray(kept.rgb).copy()
    target[y0 + 1:y1 - 1, x0 + 1:x1 - 1] = RED
    mask = np.zeros((C, C), np.float32)
    mask[y0 - 2:y1 + 2, x0 - 2:x1 + 2] = 1.0
    disks = np.arange(size, dtype=np.int32)
    frame = fill.FillFrame(
        K=K, world_to_camera=w2c, slab=slab, disks=jnp.asarray(disks), disk_valid=jnp.asarray(disks != n),
        front_rgb=jnp.zeros((C, C, 3)), front_trans=jnp.ones((C, C)), back_rgb=jnp.broadcast_to(BACKGROUND, (C, C, 3)),
        kept_rgb=kept.rgb, reach=jnp.ones((C, C), bool), target=jnp.asarray(target), mask=jnp.asarray(mask))
    # the interior, beyond the reach of the kept disks at the hole's rim (they sort first at equal depth)
    hole_px = (slice(y0 + EDGE_PX, y1 - EDGE_PX), slice(x0 + EDGE_PX, x1 - EDGE_PX))
    return params, geom, frame, n, hole_px


# One compiled program each (compiling the rasterizer dominates this file's time).
render_frame = jax.jit(fill.render_frame, static_argnames=("width", "config"))
render = jax.jit(rasterize, static_argnames=("width", "height", "config"))
step = jax.jit(fill.fill_step, static_argnames=("width", "config", "dssim_weight"))
LRS = fill.FillParams(dc=jnp.float32(0.05), opacity_logits=jnp.float32(0.05), raw_offsets=jnp.float32(0.05),
                      log_scales=jnp.float32(0.02))


def with_padding_frame(frame):
    """The frame and an empty one (zero mask), as the host driver pads batches."""
    return jax.tree.map(lambda a, b: jnp.stack([a, b]), frame, frame.replace(mask=jnp.zeros((C, C))))


@jax.jit
def loss_and_grads(params, geom, frame, slab):
    def loss(p, s):
        return fill.frame_loss(p, geom, frame.replace(slab=s), width=C, config=CONFIG, dssim_weight=DSSIM)[0]

    return jax.value_and_grad(loss, argnums=(0, 1))(params, slab)


def test_gradients_reach_only_the_new_disks(scene):
    params, geom, frame, n, _ = scene
    _, (g_params, g_slab) = loss_and_grads(params, geom, frame, frame.slab)
    for leaf in jax.tree.leaves(g_slab):
        assert np.all(np.asarray(leaf) == 0.0)  # the kept Gaussians are held fixed
    dc = np.asarray(g_params.dc)
    assert np.all(np.isfinite(dc))
    assert np.mean(np.abs(dc[:n]).sum(1) > 0) > 0.9  # the disks in view all move
    assert np.all(dc[n:] == 0.0)                     # the unlisted disk and the padding never do
    for leaf in jax.tree.leaves(g_params):
        assert np.all(np.asarray(leaf)[n:] == 0.0)


def test_layered_composition_is_the_renderer(scene):
    params, geom, frame, n, _ = scene
    rgb, overflow, _ = render_frame(params, geom, frame, width=C, config=CONFIG)
    listed = np.asarray(frame.disk_valid)
    disks = jax.tree.map(lambda x: x[listed], fill.fill_gaussians(params, geom))
    both = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), frame.slab, disks)
    direct = render(both, frame.K, frame.world_to_camera, width=C, height=C, background=BACKGROUND, config=CONFIG)
    assert not bool(overflow)
    np.testing.assert_allclose(np.asarray(rgb), np.asarray(direct.rgb), atol=COMPOSE_TOL)
    # where no disk can reach, the frame shows the kept render
    outside = frame.replace(reach=jnp.zeros((C, C), bool))
    rgb_out, _, _ = render_frame(params, geom, outside, width=C, config=CONFIG)
    np.testing.assert_array_equal(np.asarray(rgb_out), np.asarray(frame.kept_rgb))


def test_fill_gaussians_stay_on_the_plane_within_their_bounds(scene):
    params, geom, _, n, _ = scene
    rng = np.random.default_rng(0)
    wild = params.replace(raw_offsets=jnp.asarray(rng.normal(scale=10, size=params.raw_offsets.shape), jnp.float32),
                          log_scales=jnp.asarray(rng.normal(scale=5, size=params.log_scales.shape), jnp.float32))
    g = fill.fill_gaussians(wild, geom)
    offset = np.asarray(g.means - geom.centres)
    assert np.all(np.abs(offset[:, 2]) == 0.0)          # in the plane z = 0
    assert np.all(np.abs(offset[:, :2]) <= GRID + 1e-7)  # at most one cell from the grid
    scales = np.asarray(g.log_scales[:, :2])
    assert np.all(scales >= float(geom.min_log_scale) - 1e-6) and np.all(scales <= float(geom.max_log_scale) + 1e-6)
    assert np.all(np.asarray(g.opacity_logits)[n + 1:] == fill.PAD_OPACITY_LOGIT)


def test_padding_frames_do_not_change_the_loss(scene):
    params, geom, frame, _, _ = scene
    one, _ = loss_and_grads(params, geom, frame, frame.slab)
    _, _, two, (per_frame, _, _) = step(params, fill.init_state(params), geom, with_padding_frame(frame), LRS,
                                        width=C, config=CONFIG, dssim_weight=DSSIM)
    assert abs(float(one) - float(two)) < 1e-6
    assert per_frame.shape == (2,)


def test_the_fit_recovers_a_hole_of_known_colour(scene):
    params, geom, frame, n, hole_px = scene
    frames = with_padding_frame(frame)
    state = fill.init_state(params)
    p = params
    first = None
    for _ in range(STEPS):
        p, state, loss, (_, overflow, _) = step(p, state, geom, frames, LRS, width=C, config=CONFIG,
                                                dssim_weight=DSSIM)
        assert not bool(overflow)
        first = float(loss) if first is None else first
    rgb, _, _ = render_frame(p, geom, frame, width=C, config=CONFIG)
    before, _, _ = render_frame(params, geom, frame, width=C, config=CONFIG)
    err = np.abs(np.asarray(rgb)[hole_px] - RED).mean()
    assert np.abs(np.asarray(before)[hole_px] - RED).mean() > 0.2  # it started grey
    assert err < RECOVER_TOL, err
    assert float(loss) < 0.5 * first
    centre = np.max(np.abs(np.asarray(geom.centres)[:n, :2]), axis=1) < HOLE - GRID
    colours = np.asarray(p.dc)[:n][centre] * SH_C0 + 0.5
    assert np.abs(colours - RED).mean() < 2 * RECOVER_TOL
