"""A toy scene for trainer tests: random Gaussians seen by a few small cameras."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from kernels.raster import RasterConfig, rasterize
from phirie_jax.io.camera import intrinsics_matrix
from phirie_jax.types import Camera, GaussianSplatData

W, H = 48, 32


def toy_cameras(count: int = 4) -> list[Camera]:
    from phirie_jax.synthetic.scene import look_at

    K = intrinsics_matrix(40.0, 40.0, W / 2, H / 2)
    angles = np.linspace(-0.4, 0.4, count)
    return [Camera(f"{i}.png", K, look_at(np.array([2.0 * np.sin(a), -2.0 * np.cos(a), 0.3]), np.zeros(3)), W, H)
            for i, a in enumerate(angles)]


def toy_truth(rng, n: int = 64) -> GaussianSplatData:
    sh = np.zeros((n, 16, 3), np.float32)
    sh[:, 0] = rng.normal(0, 1.0, (n, 3))
    return GaussianSplatData(means=rng.uniform(-0.5, 0.5, (n, 3)).astype(np.float32),
                             quats=rng.normal(size=(n, 4)).astype(np.float32),
                             log_scales=np.log(rng.uniform(0.04, 0.12, (n, 3))).astype(np.float32),
                             opacity_logits=np.full(n, 2.0, np.float32), sh=sh)


def toy_images(truth: GaussianSplatData, cameras: list[Camera]) -> list[np.ndarray]:
    g = truth.to_kernel()
    render = jax.jit(lambda k, w: rasterize(g, k, w, width=W, height=H, config=RasterConfig(capacity=1 << 12)).rgb)
    return [np.asarray(render(jnp.asarray(c.K, jnp.float32), jnp.asarray(c.world_to_camera, jnp.float32)))
            for c in cameras]


def perturbed(truth: GaussianSplatData, rng) -> GaussianSplatData:
    """A start the trainer must improve: means moved, colours greyed, scales doubled, opacity 0.1."""
    return GaussianSplatData(means=truth.means + rng.normal(0, 0.05, truth.means.shape).astype(np.float32),
                             quats=truth.quats, log_scales=truth.log_scales + np.float32(np.log(2.0)),
                             opacity_logits=np.full(truth.num, np.log(0.1 / 0.9), np.float32), sh=truth.sh * 0.3)

