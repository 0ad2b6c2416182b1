"""The capture's 3DGS training loop: it learns, its densification statistics are right, and a
killed run resumes to the same Gaussians."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kernels import splat_fit
from kernels.raster import RasterConfig, rasterize
from phirie_jax.capture.config import TrainConfig
from phirie_jax.capture.densify import densify_and_prune, densify_on_device, padded, reset_opacity
from phirie_jax.capture.train import Views, learning_rates, sh_mask, step_spread, train_gaussians, views_psnr
from phirie_jax.types import GaussianSplatData
from tests.capture.toy import H, W, perturbed, toy_cameras, toy_images, toy_truth

# A compressed schedule for 48×32 views of Gaussians a few tenths of the extent across: densify
# after steps 10 and 20; with an opacity reset after step 20 for the resume test.
TOY = TrainConfig(steps=30, sh_band_interval=10, densify_from=10, densify_until=25, densify_interval=10,
                  opacity_reset_interval=0, checkpoint_interval=10, grad_threshold=1e-3, lr_position=1.6e-3,
                  lr_position_final=1.6e-5, lr_colour=0.02, lr_scale=0.01, lr_rotation=0.005)
TOY_RESET = dataclasses.replace(TOY, opacity_reset_interval=20)
EXTENT = 4.0          # the toy's scene scale
MIN_GAIN_DB = 3.0     # PSNR over the training views, trained against the start (measured 16.8 → 21.5)
GRAD_RTOL, GRAD_ATOL = 1e-3, 1e-8  # custom-backward screen gradients against plain autodiff (float32)


@pytest.fixture(scope="module")
def toy():
    rng = np.random.default_rng(0)
    truth = toy_truth(rng)
    cameras = toy_cameras()
    return truth, cameras, toy_images(truth, cameras), perturbed(truth, np.random.default_rng(1))


def _train(toy, **kwargs):
    _, cameras, images, start = toy
    return train_gaussians(start, Views.of(images, cameras), EXTENT, kwargs.pop("config", TOY),
                           np.random.default_rng(5), **kwargs)


def test_training_learns_and_densifies(toy):
    _, cameras, images, start = toy
    trained = _train(toy)
    views = Views.of(images, cameras)
    before = views_psnr(start, views, (0, 0, 0), RasterConfig(capacity=1 << 14))
    after = views_psnr(trained.gaussians, views, (0, 0, 0), trained.raster)
    assert after.mean() > before.mean() + MIN_GAIN_DB, (before, after)
    record = trained.record
    assert [e["step"] for e in record["densify"]] == [10, 20]
    assert record["opacity_resets"] == [] and len(trained.losses) == TOY.steps
    assert record["gaussians"] == record["densify"][-1]["gaussians"]


def test_steps_that_overflow_are_trained_again(toy, monkeypatch):
    """A buffer far too small: the steps dispatched ahead overflow, change nothing and are trained
    again with a grown buffer, so the run still makes every step and its loss falls."""
    from phirie_jax.capture import train

    monkeypatch.setattr(train, "first_capacity", lambda *args: 64)
    short = dataclasses.replace(TOY, steps=8, densify_from=100, checkpoint_interval=0)
    trained = _train(toy, config=short)
    record = trained.record
    assert record["capacity_retries"] >= 2 and trained.raster.capacity > 64  # both steps in flight overflowed
    assert len(trained.losses) == short.steps and np.all(np.isfinite(trained.losses))
    assert trained.losses[-1] < trained.losses[0]


def test_the_first_buffer_holds_every_view(toy, monkeypatch):
    """The starting capacity is counted from the views, with the margin to spare: every view's
    render fits it, however few slots a Gaussian would get by the per-Gaussian rule."""
    from phirie_jax.capture import train
    from phirie_jax.render import gaussian_bucket

    monkeypatch.setattr(train, "MIN_CAPACITY", 64)
    monkeypatch.setattr(train, "CAPACITY_PER_GAUSSIAN", 1)
    _, cameras, images, start = toy
    params, valid = padded(start, gaussian_bucket(start.num))
    capacity = train.first_capacity(params, valid, Views.of(images, cameras))
    g = splat_fit.masked_sh(params, valid, jnp.ones((params.sh.shape[1], 1)))
    count = jax.jit(lambda K, w2c: rasterize(g, K, w2c, width=W, height=H,
                                             config=RasterConfig(capacity=capacity)).num_intersections)
    needed = [int(count(jnp.asarray(c.K, jnp.float32), jnp.asarray(c.world_to_camera, jnp.float32))) for c in cameras]
    assert capacity > 64 and capacity >= train.FIRST_CAPACITY_MARGIN * max(needed)
    assert capacity & (capacity - 1) == 0


def test_killed_training_resumes_to_the_same_gaussians(toy, tmp_path):
    checkpoint = tmp_path / "checkpoint.npz"

    def kill_at_15(step, loss, count):
        if step == 15:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        _train(toy, checkpoint=checkpoint, on_step=kill_at_15, config=TOY_RESET)
    assert checkpoint.is_file()  # written after step 10, its densification included
    resumed = _train(toy, checkpoint=checkpoint, resume=True, config=TOY_RESET)
    whole = _train(toy, config=TOY_RESET, compile_ahead=True)  # the programs compiled on a thread: the same result
    assert resumed.record["resumed_at"] == 10 and whole.record["opacity_resets"] == [20]
    assert whole.record["programs_compiled_ahead"] and not resumed.record["programs_compiled_ahead"]
    for field in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(resumed.gaussians, field), getattr(whole.gaussians, field), field)
    assert resumed.losses == whole.losses and resumed.record["densify"] == whole.record["densify"]


def test_a_checkpoint_of_another_training_is_refused(toy, tmp_path):
    from phirie_jax.errors import SceneInputError

    checkpoint = tmp_path / "checkpoint.npz"
    _train(toy, checkpoint=checkpoint, config=dataclasses.replace(TOY, steps=8))
    with pytest.raises(SceneInputError, match="checkpoint of another training"):
        _train(toy, checkpoint=checkpoint, resume=True)


@pytest.mark.slow   # heavy: every view differentiated twice
def test_screen_gradient_statistics_match_plain_autodiff(toy):
    """Two steps' densification statistics: ``seen`` counts the views that showed each Gaussian,
    ``grad_sum`` adds |dL/dμ₂ₓ · W/2, dL/dμ₂ᵧ · H/2| per view, with dL/dμ₂ (the step's, through the
    compositor's custom backward) checked against plain reverse-mode autodiff of the same loss."""
    _, cameras, images, start = toy
    views = Views.of(images, cameras)
    params, valid = padded(start, 256)
    n = start.num
    raster = RasterConfig(capacity=1 << 14)
    step = jax.jit(splat_fit.train_step, static_argnames=("config", "dssim_weight", "exact_screen_gradient"))
    state, grad_sum, seen = splat_fit.init_state(params), jnp.zeros(256), jnp.zeros(256)
    expected_sum, expected_seen = np.zeros(256), np.zeros(256)
    reference = RasterConfig(capacity=1 << 14, backward="autodiff", tile_capacity=1 << 10)
    for view in (1, 2):
        def loss(offset, p=params, v=view):
            return splat_fit.view_loss(p, valid, sh_mask(TOY, 0), views.Ks[v], views.world_to_cameras[v],
                                       jnp.zeros(3), views.images[v], offset, config=reference, dssim_weight=0.2)[0]

        g = np.asarray(jax.grad(loss)(jnp.zeros((256, 2))))
        out = step(params, state, learning_rates(TOY, EXTENT, 0), valid, sh_mask(TOY, 0), views.Ks[view],
                   views.world_to_cameras[view], views.images[view], jnp.zeros(3), grad_sum, seen,
                   config=raster, dssim_weight=0.2, exact_screen_gradient=True)
        radii = np.asarray(out[5])
        expected_seen += radii > 0
        expected_sum += np.where(radii > 0, np.hypot(g[:, 0] * W / 2, g[:, 1] * H / 2), 0.0)
        params, state, _, grad_sum, seen = out[:5]
    assert np.array_equal(np.asarray(seen), expected_seen) and not expected_seen[n:].any()
    assert expected_seen.max() == 2
    np.testing.assert_allclose(np.asarray(grad_sum), expected_sum, rtol=GRAD_RTOL, atol=GRAD_ATOL)


def test_densification_counts_of_a_hand_checked_case():
    """Six Gaussians, extent 1: #0 high gradient & small → cloned; #2 high & large → split in two;
    #4 transparent → pruned; #5 huge → pruned only when large ones are (after the first reset)."""
    n = 6
    data = GaussianSplatData(
        means=np.zeros((n, 3), np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        log_scales=np.log(np.float32([[0.005] * 3, [0.005] * 3, [0.05] * 3, [0.05] * 3, [0.005] * 3, [0.5] * 3])),
        opacity_logits=np.float32([2, 2, 2, 2, -9, 2]), sh=np.zeros((n, 1, 3), np.float32))
    grad = np.float32([3e-4, 1e-4, 5e-4, 1e-4, 0, 0])
    noise = np.random.default_rng(0).normal(size=(2, n, 3))
    early, _, early_counts = densify_and_prune(data, grad, 1.0, TrainConfig(), noise, prune_large=False)
    assert early_counts == {"cloned": 1, "split": 1, "pruned": 1} and early.num == 7  # 6 + 1 + 2 − 1 − 1
    later, source, counts = densify_and_prune(data, grad, 1.0, TrainConfig(), noise)
    assert counts == {"cloned": 1, "split": 1, "pruned": 2} and later.num == 6
    assert sorted(source.tolist()) == [-1, -1, -1, 0, 1, 3]  # the clone and both children start afresh
    capped = dataclasses.replace(TrainConfig(), max_gaussians=7)  # room for one: the highest gradient (#2)
    _, _, counts = densify_and_prune(data, grad, 1.0, capped, noise)
    assert counts["split"] == 1 and counts["cloned"] == 0
    # the same case on the device, as training densifies
    params, valid = padded(data, 256)
    sums = jnp.asarray(np.concatenate([grad, np.zeros(250, np.float32)]))
    for prune_large, want in ((False, {"count": 7, "cloned": 1, "split": 1, "pruned": 1}),
                              (True, {"count": 6, "cloned": 1, "split": 1, "pruned": 2})):
        *_, device_counts = densify_on_device(params, valid, splat_fit.init_state(params), sums, jnp.ones(256), 1.0,
                                              TrainConfig(), jax.random.key(0), prune_large)
        assert device_counts == want


def test_opacity_reset_clamps_and_clears_the_moments():
    data = GaussianSplatData(means=np.zeros((3, 3), np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (3, 1)),
                             log_scales=np.full((3, 3), -3, np.float32), opacity_logits=np.float32([-6, 0, 4]),
                             sh=np.zeros((3, 1, 3), np.float32))
    params, _ = padded(data, 4)
    state = splat_fit.init_state(params)
    adam = state[0]._replace(mu=jax.tree.map(jnp.ones_like, state[0].mu), nu=jax.tree.map(jnp.ones_like, state[0].nu))
    params, (adam, *_) = reset_opacity(params, (adam, *state[1:]), 0.01)
    np.testing.assert_allclose(jax.nn.sigmoid(params.opacity_logits[:3]), [jax.nn.sigmoid(-6.0), 0.01, 0.01],
                               rtol=1e-5)
    assert not np.asarray(adam.mu.opacity_logits).any() and not np.asarray(adam.nu.opacity_logits).any()
    assert np.asarray(adam.mu.means).all()  # the other moments are kept


def test_step_spread_names_the_slow_intervals():
    times = [0.01] * 95 + [0.5, 0.04, 0.02, 0.019, 0.03]   # a compilation, host stalls, steps at 2× the median
    spread = step_spread(times)
    assert spread["step_s_quantiles"]["0.5"] == 0.01
    assert spread["slow_steps"] == 3 and spread["slow_steps_s"] == pytest.approx(0.57)
    assert len(spread["step_s_by_tenth"]) == 10 and spread["step_s_by_tenth"][0] == 0.01
    assert spread["step_s_mean"] == pytest.approx(np.mean(times), abs=1e-5)
    assert step_spread([]) == {}
