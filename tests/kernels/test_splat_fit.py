"""The 3DGS training step: its loss, its view-space gradient and that it learns."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from kernels import splat_fit
from kernels.gaussians import Gaussians
from kernels.image_metrics import ssim
from kernels.project import project_gaussians
from kernels.raster import RasterConfig, rasterize

W, H = 32, 24
K = np.array([[30.0, 0, W / 2], [0, 30.0, H / 2], [0, 0, 1]], np.float32)
SCREEN_GRAD_RTOL = 1e-4  # exact for a mean on the optical axis (float32)


def _gaussians(rng, n=16) -> Gaussians:
    return Gaussians(means=jnp.asarray(np.c_[rng.uniform(-0.3, 0.3, (n, 2)), rng.uniform(1.5, 2.5, n)], jnp.float32),
                     quats=jnp.asarray(rng.normal(size=(n, 4)), jnp.float32),
                     log_scales=jnp.full((n, 3), np.log(0.08), jnp.float32),
                     opacity_logits=jnp.full(n, 1.0, jnp.float32),
                     sh=jnp.asarray(rng.normal(0, 0.5, (n, 16, 3)), jnp.float32))


def test_photometric_loss_is_the_3dgs_loss():
    rng = np.random.default_rng(0)
    a, b = (jnp.asarray(rng.uniform(size=(H, W, 3)), jnp.float32) for _ in range(2))
    expected = 0.8 * jnp.mean(jnp.abs(a - b)) + 0.2 * (1.0 - ssim(a, b))
    np.testing.assert_allclose(splat_fit.photometric_loss(a, b, 0.2), expected, rtol=1e-6)
    assert float(splat_fit.photometric_loss(a, a, 0.2)) < 1e-6


def test_screen_gradient_on_the_axis_is_the_gradient_at_the_projected_mean():
    w2c = np.eye(4, dtype=np.float32)
    mean = jnp.asarray([[0.0, 0.0, 2.0]], jnp.float32)
    coeff = jnp.asarray([0.7, -0.3], jnp.float32)  # L = 0.7 u − 0.3 v
    g = Gaussians(means=mean, quats=jnp.asarray([[1.0, 0, 0, 0]]), log_scales=jnp.full((1, 3), -3.0),
                  opacity_logits=jnp.zeros(1), sh=jnp.zeros((1, 1, 3)))

    def loss(means):
        p = project_gaussians(g.replace(means=means), jnp.asarray(K), jnp.asarray(w2c), width=W, height=H)
        return jnp.sum(p.means2d[0] * coeff)

    grad = jax.grad(loss)(mean)
    got = splat_fit.screen_gradient(grad, mean, jnp.asarray(K), jnp.asarray(w2c), W, H)
    expected = np.hypot(0.7 * W / 2, -0.3 * H / 2)
    np.testing.assert_allclose(np.asarray(got), [expected], rtol=SCREEN_GRAD_RTOL)


def test_train_step_lowers_the_loss_and_counts_visibility():
    rng = np.random.default_rng(1)
    truth = _gaussians(rng)
    config = RasterConfig(capacity=1 << 12)
    Ks = jnp.asarray(np.stack([K, K]))
    w2cs = np.stack([np.eye(4, dtype=np.float32)] * 2)
    w2cs[1, 0, 3] = 0.1
    w2cs = jnp.asarray(w2cs)
    bg = jnp.zeros(3)
    images = jax.jit(jax.vmap(lambda k, w: rasterize(truth, k, w, width=W, height=H, background=bg,
                                                     config=config).rgb))(Ks, w2cs)
    params = truth.replace(means=truth.means + jnp.asarray(rng.normal(0, 0.05, (16, 3)), jnp.float32),
                           sh=truth.sh * 0.3)
    state = splat_fit.init_state(params)
    lrs = Gaussians(means=jnp.float32(0.01), quats=jnp.float32(0.01), log_scales=jnp.float32(0.01),
                    opacity_logits=jnp.float32(0.05), sh=jnp.float32(0.05))
    valid, sh_mask = jnp.ones(16, bool), jnp.ones((16, 1))
    grad_sum, seen = jnp.zeros(16), jnp.zeros(16)
    step = jax.jit(splat_fit.train_step, static_argnames=("config", "dssim_weight"))
    losses = []
    for i in range(30):
        params, state, loss, grad_sum, seen, radii, overflow, _ = step(
            params, state, lrs, valid, sh_mask, Ks[i % 2], w2cs[i % 2], images[i % 2], bg, grad_sum, seen,
            config=config, dssim_weight=0.2)
        assert not bool(overflow)
        losses.append(float(loss))
    assert losses[-1] < 0.5 * losses[0]
    assert float(jnp.max(seen)) <= 30 and float(jnp.sum(seen)) > 0 and bool(jnp.all(grad_sum >= 0))
