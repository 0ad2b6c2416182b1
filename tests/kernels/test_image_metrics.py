"""PSNR / SSIM against a direct NumPy implementation (a loop over pixels) and by their properties."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from kernels.image_metrics import masked_l1_dssim, masked_mean, psnr, ssim, ssim_map

SSIM_TOL = 1e-4   # float32 JAX vs float64 loop
PSNR_TOL = 1e-3   # dB


def ssim_reference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SSIM per pixel the slow way: at every pixel, Gaussian-weighted statistics of its 11×11
    neighbourhood, zero padded (what the 3DGS training loss computes), per channel, then averaged."""
    size, sigma = 11, 1.5
    x = np.arange(size) - (size - 1) / 2
    g = np.exp(-0.5 * (x / sigma) ** 2)
    g /= g.sum()
    window = np.outer(g, g)
    c1, c2 = 0.01**2, 0.03**2
    h, w, c = a.shape
    pad = size // 2
    ap = np.pad(a.astype(np.float64), ((pad, pad), (pad, pad), (0, 0)))
    bp = np.pad(b.astype(np.float64), ((pad, pad), (pad, pad), (0, 0)))
    out = np.zeros((h, w))
    for i in range(h):
        for j in range(w):
            vals = []
            for ch in range(c):
                pa, pb = ap[i:i + size, j:j + size, ch], bp[i:i + size, j:j + size, ch]
                mu_a, mu_b = np.sum(window * pa), np.sum(window * pb)
                va = np.sum(window * pa * pa) - mu_a**2
                vb = np.sum(window * pb * pb) - mu_b**2
                cov = np.sum(window * pa * pb) - mu_a * mu_b
                vals.append((2 * mu_a * mu_b + c1) * (2 * cov + c2) / ((mu_a**2 + mu_b**2 + c1) * (va + vb + c2)))
            out[i, j] = np.mean(vals)
    return out


def test_ssim_map_matches_the_pixel_loop():
    rng = np.random.default_rng(0)
    a = rng.uniform(size=(13, 17, 3)).astype(np.float32)
    b = np.clip(a + rng.normal(scale=0.1, size=a.shape), 0, 1).astype(np.float32)
    ours = np.asarray(ssim_map(jnp.asarray(a), jnp.asarray(b)))
    np.testing.assert_allclose(ours, ssim_reference(a, b), atol=SSIM_TOL)


def test_ssim_properties():
    rng = np.random.default_rng(1)
    a = jnp.asarray(rng.uniform(size=(20, 24, 3)), jnp.float32)
    b = jnp.asarray(rng.uniform(size=(20, 24, 3)), jnp.float32)
    assert abs(float(ssim(a, a)) - 1.0) < 1e-5
    assert abs(float(ssim(a, b)) - float(ssim(b, a))) < 1e-6
    assert float(ssim(a, b)) < 0.5  # independent noise is not similar
    assert float(ssim(a, 0.5 * a + 0.5 * b)) > float(ssim(a, b))


def test_psnr_of_a_constant_error_and_under_a_mask():
    a = jnp.full((8, 9, 3), 0.5)
    assert abs(float(psnr(a, a + 0.1)) - 20.0) < PSNR_TOL  # 10 log10(1 / 0.01)
    b = a.at[:4].add(0.1)
    mask = jnp.zeros((8, 9), bool).at[:4].set(True)
    assert abs(float(psnr(a, b, mask)) - 20.0) < PSNR_TOL
    assert float(psnr(a, b, ~mask)) > 100.0  # identical there
    assert np.isfinite(float(psnr(a, a)))


def test_masked_mean_weights_and_empty_mask():
    x = jnp.arange(12.0).reshape(3, 4)
    mask = jnp.zeros((3, 4)).at[0, 0].set(1.0).at[2, 3].set(3.0)
    assert float(masked_mean(x, mask)) == (0.0 * 1 + 11.0 * 3) / 4
    assert float(masked_mean(x, jnp.zeros((3, 4)))) == 0.0


def test_masked_loss_ignores_what_is_far_outside_the_mask():
    rng = np.random.default_rng(2)
    target = jnp.asarray(rng.uniform(size=(40, 40, 3)), jnp.float32)
    mask = jnp.zeros((40, 40), bool).at[5:15, 5:15].set(True)
    assert float(masked_l1_dssim(target, target, mask, 0.2)) < 1e-6
    far = target.at[30:, 30:].set(0.0)  # > one SSIM window (5 px) away from the mask
    assert float(masked_l1_dssim(far, target, mask, 0.2)) < 1e-6
    near = target.at[8:10, 8:10].set(0.0)
    assert float(masked_l1_dssim(near, target, mask, 0.2)) > 1e-3
