"""Crops: render a square window of a camera around a region instead of the whole image.

A crop is a ``Camera`` whose K is shifted (and scaled when the region is larger than the
largest crop size) so that its C × C pixels cover the window; C is one of a few static sizes,
so every crop of a pass shares one compiled program. At scale 1 a crop pixel is exactly a
full-image pixel (integer origin), so masks and images are sampled without interpolation.

Only Gaussians that can touch the window are rendered: the host culls by a conservative
3σ screen radius (the kernel's EWA radius is at most this; see ``screen_radius_bound``), and
pads every subset of a pass to one power-of-two count so the pass compiles once.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from kernels.project import NEAR_PLANE, SCREEN_DILATION, SIGMA_EXTENT
from kernels.sh import sh_basis, sh_degree_from_coeffs
from phirie_jax.geometry import logit
from phirie_jax.render import Renderer, gaussian_bucket, pad_gaussians
from phirie_jax.types import Camera, GaussianSplatData

CULL_MARGIN_PX = 2.0  # slack on top of the radius bound (tile rounding is the kernel's business)
ALPHA_MIN = 1.0 / 255.0


@dataclasses.dataclass(frozen=True)
class Crop:
    """A C × C window of camera ``view``; crop pixel (j, i) ↔ full pixel (ox + j/s, oy + i/s)."""

    view: int
    camera: Camera          # the crop camera (width = height = size)
    origin: tuple[int, int]  # (ox, oy) full-image pixel of the crop's corner
    scale: float            # crop pixels per full-image pixel (≤ 1)
    size: int
    inside: np.ndarray      # (C, C) bool: the crop pixel lies inside the full image

    def full_pixels(self) -> tuple[np.ndarray, np.ndarray]:
        """(C, C) int row and column of the full-image pixel under each crop pixel (clipped)."""
        j = np.arange(self.size)
        cols = np.floor(self.origin[0] + (j + 0.5) / self.scale).astype(np.int64)
        rows = np.floor(self.origin[1] + (j + 0.5) / self.scale).astype(np.int64)
        return np.broadcast_to(rows[:, None], (self.size, self.size)), np.broadcast_to(cols[None], (self.size, self.size))

    def sample(self, image: np.ndarray, full_width: int, full_height: int) -> np.ndarray:
        """Nearest-pixel crop of a full image (H, W, ...) → (C, C, ...); zeros outside it."""
        rows, cols = self.full_pixels()
        out = image[np.clip(rows, 0, full_height - 1), np.clip(cols, 0, full_width - 1)]
        return np.where(self.inside.reshape(self.inside.shape + (1,) * (out.ndim - 2)), out, 0)

    def to_full(self, uv: np.ndarray) -> np.ndarray:
        """(P, 2) crop pixel coordinates → full-image pixel coordinates."""
        return uv / self.scale + np.asarray(self.origin, np.float64)


def make_crop(camera: Camera, view: int, box: np.ndarray, sizes: tuple[int, ...], margin: int) -> Crop:
    """The crop of the smallest size in ``sizes`` holding ``box`` (x0, y0, x1, y1 full pixels, inclusive)
    plus ``margin`` pixels each side; larger boxes take the largest size at a reduced scale."""
    x0, y0, x1, y1 = (float(v) for v in box)
    extent = max(x1 - x0 + 1, y1 - y0 + 1) + 2 * margin
    size = next((s for s in sorted(sizes) if s >= extent), max(sizes))
    scale = min(1.0, size / extent)
    span = size / scale  # full-image pixels covered
    cx, cy = 0.5 * (x0 + x1 + 1), 0.5 * (y0 + y1 + 1)
    ox, oy = cx - span / 2, cy - span / 2
    # keep the window inside the image where it fits, so no crop pixel is wasted
    ox = min(max(ox, 0.0), max(camera.width - span, 0.0)) if span <= camera.width else (camera.width - span) / 2
    oy = min(max(oy, 0.0), max(camera.height - span, 0.0)) if span <= camera.height else (camera.height - span) / 2
    if scale == 1.0:
        ox, oy = float(np.floor(ox)), float(np.floor(oy))
    K = np.asarray(camera.K, np.float64).copy()
    K[0, 2] -= ox
    K[1, 2] -= oy
    K[:2] *= scale
    cam = dataclasses.replace(camera, K=K, width=size, height=size, name=f"{camera.name}#crop")
    j = np.arange(size)
    col_in = (ox + (j + 0.5) / scale >= 0) & (ox + (j + 0.5) / scale < camera.width)
    row_in = (oy + (j + 0.5) / scale >= 0) & (oy + (j + 0.5) / scale < camera.height)
    return Crop(view, cam, (ox, oy) if scale < 1.0 else (int(ox), int(oy)), scale, size,
                row_in[:, None] & col_in[None, :])


def screen_radius_bound(data: GaussianSplatData, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel centres (N, 2), view depths (N,) and an upper bound (N,) of the kernel's 3σ radius.

    λ_max(J W Σ Wᵀ Jᵀ) ≤ ‖J‖² s_max² and ‖J‖ ≤ f / z · (1 + |x/z| + |y/z|) (f the larger focal),
    plus the kernel's screen dilation.
    """
    means = data.means.astype(np.float64)
    cam = means @ camera.world_to_camera[:3, :3].T + camera.world_to_camera[:3, 3]
    z = cam[:, 2]
    zs = np.where(z > NEAR_PLANE, z, 1.0)
    uv = (cam[:, :2] / zs[:, None]) @ camera.K[:2, :2].T + camera.K[:2, 2]
    focal = float(max(abs(camera.K[0, 0]), abs(camera.K[1, 1])))
    stretch = focal / zs * (1.0 + np.abs(cam[:, 0] / zs) + np.abs(cam[:, 1] / zs))
    s_max = np.exp(data.log_scales.astype(np.float64).max(axis=1))
    radius = SIGMA_EXTENT * np.sqrt((stretch * s_max) ** 2 + SCREEN_DILATION) + CULL_MARGIN_PX
    return uv, z, radius


def cull(data: GaussianSplatData, camera: Camera, candidates: np.ndarray | None = None) -> np.ndarray:
    """Indices (into ``data``) of the Gaussians that can touch the image of ``camera``."""
    idx = np.arange(data.num) if candidates is None else np.asarray(candidates, np.int64)
    sub = data.subset(idx) if candidates is not None else data
    uv, z, r = screen_radius_bound(sub, camera)
    opaque = sub.opacity_logits.astype(np.float64) >= logit(ALPHA_MIN)
    keep = (z > NEAR_PLANE) & opaque & (uv[:, 0] + r >= 0) & (uv[:, 0] - r <= camera.width) \
        & (uv[:, 1] + r >= 0) & (uv[:, 1] - r <= camera.height)
    return idx[keep]


def view_colours(data: GaussianSplatData, camera: Camera) -> np.ndarray:
    """(N, 3) the colour each Gaussian shows to this camera (its SH along the view ray)."""
    d = data.means.astype(np.float64) - camera.center
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    basis = sh_basis(d, sh_degree_from_coeffs(data.sh.shape[1]))  # (N, K)
    return np.maximum(np.einsum("nk,nkc->nc", basis, data.sh.astype(np.float64)) + 0.5, 0.0)


class CropRenderer:
    """Renders Gaussian subsets into crops, every subset of a pass padded to one count."""

    def __init__(self, renderer: Renderer | None = None):
        self.renderer = renderer or Renderer()
        self.renders = 0

    def render(self, data: GaussianSplatData, crop: Crop, pad_to: int, features: np.ndarray | None = None,
               num_features: int = 2, background=None):
        """RasterOutput of ``data`` (≤ ``pad_to`` Gaussians) in the crop. features: (N, F ≤ num_features)."""
        if data.num > pad_to:
            raise ValueError(f"{data.num} Gaussians do not fit the pass's padded count {pad_to}")
        feats = np.zeros((pad_to, num_features), np.float32)
        if features is not None and data.num:
            feats[: data.num, : features.shape[1]] = features
        g = pad_gaussians(data.to_kernel(), pad_to)
        bg = None if background is None else np.asarray(background, np.float32)
        self.renders += 1
        return self.renderer.render(g, crop.camera, features=jnp.asarray(feats), background=bg)


def pass_bucket(counts: list[int]) -> int:
    """The padded Gaussian count of a pass: the power-of-two bucket of its largest subset."""
    return gaussian_bucket(max([1, *counts]))
