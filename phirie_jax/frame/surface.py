"""The splat-derived surface, cheaply: per coarse pixel of a few views, the Gaussian at which
the front-to-back composite of the splats becomes opaque.

Observation fuses the full surface later (``phirie_jax.observe.surface``: rendered depth at
every camera, a TSDF at 5 mm); the frame is decided before that, in the capture's units, so it
takes what the renders' median depth would show, for a fraction of the cost: up to
``VIEWS`` cameras, each a grid ``WIDTH`` pixels wide. Every Gaussian is composited into the
pixel its centre falls in, front to back, with alpha = opacity × the share of the pixel its
footprint covers (2πσ², σ its two largest scales in pixels); the first Gaussian after which
less than half the light passes is that pixel's surface point (the median depth of the
composite). Pixels the splats never make half opaque give none.
"""

from __future__ import annotations

import numpy as np

from phirie_jax.geometry import sigmoid
from phirie_jax.threads import map_on_cores
from phirie_jax.types import Camera, GaussianSplatData

VIEWS = 16
WIDTH = 96
MIN_OPACITY = 0.02       # fainter Gaussians do not change where the composite turns opaque
SURFACE_TRANSMITTANCE = 0.5


def view_indices(count: int, views: int = VIEWS) -> np.ndarray:
    """Up to ``views`` camera indices spread evenly over ``count`` cameras."""
    return np.unique(np.linspace(0, count - 1, min(views, count)).round().astype(int)) if count else np.zeros(0, int)


def composite_surface(means: np.ndarray, opacity: np.ndarray, sigma: np.ndarray, camera: Camera,
                      width: int = WIDTH) -> np.ndarray:
    """Indices of the Gaussians that are ``camera``'s surface, one per coarse pixel at most.

    means (N, 3), opacity (N,), sigma (N,) the footprint's world-space σ (geometric mean of the
    two largest scales)."""
    from phirie_jax.frame.estimate import project

    cam = camera.scaled(width / camera.width)
    uv, depth = project(cam, means)
    cols, rows = np.floor(uv[:, 0]), np.floor(uv[:, 1])
    inside = (depth > 0) & (cols >= 0) & (cols < cam.width) & (rows >= 0) & (rows < cam.height)
    index = np.flatnonzero(inside)
    if not len(index):
        return index
    pixel = rows[index].astype(np.int64) * cam.width + cols[index].astype(np.int64)
    footprint = 2 * np.pi * (cam.K[0, 0] * sigma[index] / depth[index]) ** 2
    alpha = np.clip(opacity[index] * np.minimum(1.0, footprint), 0.0, 0.999)
    order = np.lexsort((depth[index], pixel))
    pixel, alpha, index = pixel[order], alpha[order], index[order]
    log_t = np.cumsum(np.log1p(-alpha))                       # running over all pixels ...
    starts = np.flatnonzero(np.r_[True, pixel[1:] != pixel[:-1]])
    group = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(pixel)]))
    before = np.r_[0.0, log_t][starts][group]                 # ... minus what came before this pixel
    opaque = (log_t - before) < np.log(SURFACE_TRANSMITTANCE)
    hit = np.flatnonzero(opaque)                              # ascending: by pixel, then depth
    first = hit[np.r_[True, group[hit][1:] != group[hit][:-1]]] if len(hit) else hit
    return np.sort(index[first])


def surface_points(gaussians: GaussianSplatData, cameras: tuple[Camera, ...], views: int = VIEWS,
                   width: int = WIDTH) -> np.ndarray:
    """(P, 3) centres of the Gaussians that form the composited surface of up to ``views``
    cameras (each Gaussian once)."""
    opacity = sigmoid(gaussians.opacity_logits.astype(np.float64))
    keep = np.flatnonzero(opacity >= MIN_OPACITY)
    means = gaussians.means[keep].astype(np.float64)
    scales = np.sort(np.exp(gaussians.log_scales[keep].astype(np.float64)), axis=1)
    sigma = np.sqrt(scales[:, 1] * scales[:, 2])
    opacity = opacity[keep]
    found = map_on_cores(lambda i: composite_surface(means, opacity, sigma, cameras[i], width),
                         view_indices(len(cameras), views), "frame surface")
    return means[np.unique(np.concatenate(found))] if found else np.zeros((0, 3))
