"""Crops: render a square window of a camera around a region instead of the whole image.

A crop is a ``Camera`` whose K is shifted (and scaled when the region is larger than the
largest crop size) so that its C × C pixels cover the window; C is one of a few static sizes,
so every crop of a pass shares one compiled program. At scale 1 a crop pixel is exactly a
full-image pixel (integer origin), so masks and images are sampled without interpolation.

Only Gaussians that can touch the window are rendered: the host culls by a conservative
3σ screen radius (the kernel's EWA radius is at most this; see ``screen_radius_bound``), and
pads every subset of a pass to one power-of-two count so the pass compiles once.

The padding is done on the host (NumPy) and the padded arrays copied to the device as they are
(``to_device``), so a subset of a new size costs a transfer, never a program: padded on the
device, every distinct size compiled its own small programs (on the CPU, 384 compilations for
the four objects of a ``default`` scene). ``CropRenderer.render_many``
renders the crops of a pass in batches of ``batch_size`` (one launch each, one program per
batch size), every crop of a batch with its own Gaussian subset, features and background.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from kernels.gaussians import Gaussians
from kernels.project import NEAR_PLANE, SCREEN_DILATION, SIGMA_EXTENT
from kernels.raster import DEPTH_EPS
from kernels.sh import rgb_to_sh_dc, sh_basis, sh_degree_from_coeffs
from phirie_jax.geometry import logit
from phirie_jax.render import PAD_OPACITY_LOGIT, Renderer, gaussian_bucket, next_power_of_two
from phirie_jax.types import Camera, GaussianSplatData

CULL_MARGIN_PX = 2.0  # slack on top of the radius bound (tile rounding is the kernel's business)
ALPHA_MIN = 1.0 / 255.0
MAX_BATCH = 16                 # crops per launch of ``render_many``
BATCH_GAUSSIANS = 1 << 21      # ... and at most this many (padded) Gaussians per launch (device memory)


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
    return _radius_bound(data.means.astype(np.float64), np.exp(data.log_scales.astype(np.float64).max(axis=1)),
                         camera)


def _radius_bound(means: np.ndarray, s_max: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``screen_radius_bound`` of centres (N, 3) float64 with largest σ (N,)."""
    cam = means @ camera.world_to_camera[:3, :3].T + camera.world_to_camera[:3, 3]
    z = cam[:, 2]
    zs = np.where(z > NEAR_PLANE, z, 1.0)
    uv = (cam[:, :2] / zs[:, None]) @ camera.K[:2, :2].T + camera.K[:2, 2]
    focal = float(max(abs(camera.K[0, 0]), abs(camera.K[1, 1])))
    stretch = focal / zs * (1.0 + np.abs(cam[:, 0] / zs) + np.abs(cam[:, 1] / zs))
    radius = SIGMA_EXTENT * np.sqrt((stretch * s_max) ** 2 + SCREEN_DILATION) + CULL_MARGIN_PX
    return uv, z, radius


def _visible(uv: np.ndarray, z: np.ndarray, r: np.ndarray, opaque: np.ndarray, camera: Camera) -> np.ndarray:
    return (z > NEAR_PLANE) & opaque & (uv[:, 0] + r >= 0) & (uv[:, 0] - r <= camera.width) \
        & (uv[:, 1] + r >= 0) & (uv[:, 1] - r <= camera.height)


def cull(data: GaussianSplatData, camera: Camera, candidates: np.ndarray | None = None) -> np.ndarray:
    """Indices (into ``data``) of the Gaussians that can touch the image of ``camera``."""
    idx = np.arange(data.num) if candidates is None else np.asarray(candidates, np.int64)
    sub = data.subset(idx) if candidates is not None else data
    uv, z, r = screen_radius_bound(sub, camera)
    opaque = sub.opacity_logits.astype(np.float64) >= logit(ALPHA_MIN)
    return idx[_visible(uv, z, r, opaque, camera)]


@dataclasses.dataclass(frozen=True)
class Footprints:
    """What ``screen_radius_bound`` and ``cull`` read of a Gaussian set, prepared once for the
    many crops of a pass (each frame of the target pass culls the whole capture: converting the
    centres and scales again per frame, and copying the subset's SH, was most of its host time).

    ``cull`` returns what ``views.cull`` returns, and the bound of those Gaussians as
    ``screen_radius_bound`` gives it (the same arithmetic)."""

    means: np.ndarray   # (N, 3) float64
    s_max: np.ndarray   # (N,) largest σ
    opaque: np.ndarray  # (N,) bool: opacity ≥ ALPHA_MIN

    @classmethod
    def of(cls, data: GaussianSplatData) -> Footprints:
        return cls(data.means.astype(np.float64), np.exp(data.log_scales.astype(np.float64).max(axis=1)),
                   data.opacity_logits.astype(np.float64) >= logit(ALPHA_MIN))

    def cull(self, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Indices (K,) of the Gaussians that can touch the camera's image, their pixel centres
        (K, 2), view depths (K,) and radius bounds (K,)."""
        return ViewProjection.of(self, camera).cull(camera)


@dataclasses.dataclass(frozen=True)
class ViewProjection:
    """The opaque Gaussians in front of one camera pose, projected once: every crop of that view
    (``make_crop``: the same pose, its intrinsics scaled and shifted) is culled from it without
    transforming the capture again (a pass renders many crops of few views).

    ``_radius_bound``'s arithmetic with the focal length factored out: uv = (x/z, y/z) K₂ + c and
    the radius bound 3·sqrt((f·q)² + dilation) + margin, q = s_max (1 + |x/z| + |y/z|) / z."""

    index: np.ndarray      # (M,) the Gaussians in front of the camera and opaque
    normalized: np.ndarray  # (M, 2) x/z, y/z
    z: np.ndarray          # (M,) view depth
    spread: np.ndarray     # (M,) q

    @classmethod
    def of(cls, footprints: Footprints, camera: Camera) -> ViewProjection:
        rotation, translation = camera.world_to_camera[:3, :3], camera.world_to_camera[:3, 3]
        cam = footprints.means @ rotation.T + translation
        index = np.flatnonzero((cam[:, 2] > NEAR_PLANE) & footprints.opaque)
        cam, s_max = cam[index], footprints.s_max[index]
        normalized = cam[:, :2] / cam[:, 2:3]
        spread = s_max * (1.0 + np.abs(normalized[:, 0]) + np.abs(normalized[:, 1])) / cam[:, 2]
        return cls(index, normalized, cam[:, 2], spread)

    def cull(self, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``Footprints.cull`` for ``camera``, which has this projection's pose (a crop of its view)."""
        uv = self.normalized @ camera.K[:2, :2].T + camera.K[:2, 2]
        focal = float(max(abs(camera.K[0, 0]), abs(camera.K[1, 1])))
        r = SIGMA_EXTENT * np.sqrt((focal * self.spread) ** 2 + SCREEN_DILATION) + CULL_MARGIN_PX
        keep = np.flatnonzero((uv[:, 0] + r >= 0) & (uv[:, 0] - r <= camera.width)
                              & (uv[:, 1] + r >= 0) & (uv[:, 1] - r <= camera.height))
        return self.index[keep], uv[keep], self.z[keep], r[keep]


def tile_rects(uv: np.ndarray, r: np.ndarray, size: int, tile: int) -> tuple[np.ndarray, ...]:
    """Inclusive tile ranges x0, x1, y0, y1 (each (N,) int) of a C × C crop's ``tile``-pixel tiles
    that the discs (uv (N, 2), radius r (N,)) touch, as the kernel bins them (``kernels.project``:
    floor((centre ± radius) / tile), clipped); x1 < x0 or y1 < y0: none. With the radius bound
    of ``screen_radius_bound`` these hold every tile the kernel puts the Gaussian in."""
    tiles = -(-size // tile)

    def span(centre):
        lo = np.floor(np.clip((centre - r) / tile, -1.0, tiles))
        hi = np.floor(np.clip((centre + r) / tile, -1.0, tiles))
        return np.maximum(lo, 0).astype(np.int64), np.minimum(hi, tiles - 1).astype(np.int64)

    return (*span(uv[:, 0]), *span(uv[:, 1]))


def view_colours(data: GaussianSplatData, camera: Camera) -> np.ndarray:
    """(N, 3) the colour each Gaussian shows to this camera (its SH along the view ray)."""
    d = data.means.astype(np.float64) - camera.center
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    basis = sh_basis(d, sh_degree_from_coeffs(data.sh.shape[1]))  # (N, K)
    return np.maximum(np.einsum("nk,nkc->nc", basis, data.sh.astype(np.float64)) + 0.5, 0.0)


@dataclasses.dataclass(frozen=True)
class CropImage:
    """One crop's render on the host (the kernel's ``RasterOutput`` fields, as NumPy)."""

    rgb: np.ndarray       # (C, C, 3)
    alpha: np.ndarray     # (C, C)
    depth: np.ndarray     # (C, C) Σ wᵢ zᵢ, not normalized
    features: np.ndarray  # (C, C, F)

    @property
    def depth_normalized(self) -> np.ndarray:
        """(C, C) expected depth of what was hit (0 where nothing was), as the kernel's."""
        return np.where(self.alpha > 0, self.depth / np.maximum(self.alpha, np.float32(DEPTH_EPS)), 0.0
                        ).astype(np.float32)


@dataclasses.dataclass(frozen=True)
class CropJob:
    """One render of a pass: ``data`` (or its ``index`` subset, taken only while its batch is built)
    in ``crop``; features (N, F ≤ the pass's count) per Gaussian of the subset; background (3,)."""

    data: GaussianSplatData
    crop: Crop
    index: np.ndarray | None = None
    features: np.ndarray | None = None
    background: np.ndarray | None = None

    @property
    def num(self) -> int:
        return self.data.num if self.index is None else len(self.index)

    def gaussians(self) -> GaussianSplatData:
        return self.data if self.index is None else self.data.subset(self.index)


def padded(data: GaussianSplatData, pad_to: int, sh_coeffs: int | None = None) -> dict[str, np.ndarray]:
    """The kernel's Gaussian arrays of ``data`` padded on the host to ``pad_to`` with the renderer's
    transparent Gaussians (``render.pad_gaussians``' values) and, with ``sh_coeffs``, its SH padded
    with zero coefficients (which add nothing to a colour) to that many."""
    n = data.num
    if n > pad_to:
        raise ValueError(f"{n} Gaussians do not fit the pass's padded count {pad_to}")
    out = _pad_rows(1, pad_to, data.sh.shape[1] if sh_coeffs is None else sh_coeffs)
    _fill_rows(out, 0, data, None)
    return {k: v[0] for k, v in out.items()}


def _pad_rows(batch: int, pad_to: int, sh_coeffs: int) -> dict[str, np.ndarray]:
    """(batch, pad_to, ...) kernel arrays of the renderer's transparent padding Gaussians."""
    return {"means": np.zeros((batch, pad_to, 3), np.float32), "quats": np.ones((batch, pad_to, 4), np.float32),
            "log_scales": np.full((batch, pad_to, 3), -10.0, np.float32),
            "opacity_logits": np.full((batch, pad_to), PAD_OPACITY_LOGIT, np.float32),
            "sh": np.zeros((batch, pad_to, sh_coeffs, 3), np.float32)}


def _fill_rows(out: dict[str, np.ndarray], b: int, data: GaussianSplatData, index: np.ndarray | None) -> None:
    """Row ``b`` of ``_pad_rows`` arrays starts with ``data`` (or its ``index`` subset), taken
    straight from its arrays (no subset copied first); SH coefficients past ``data``'s stay 0 and
    those past the rows' are dropped."""
    n = data.num if index is None else len(index)
    if n > out["means"].shape[1]:
        raise ValueError(f"{n} Gaussians do not fit the pass's padded count {out['means'].shape[1]}")
    k = min(out["sh"].shape[2], data.sh.shape[1])
    for name in ("means", "quats", "log_scales", "opacity_logits"):
        src = getattr(data, name)
        out[name][b, :n] = src if index is None else src[index]
    out["sh"][b, :n, :k] = (data.sh if index is None else data.sh[index])[:, :k]


def colourless(data: GaussianSplatData) -> GaussianSplatData:
    """``data`` with its SH cut to the DC term (a view: nothing is copied), for a pass that reads
    only alpha, depth and features: the kernel's colour is not in them, and a pass of DC-only
    Gaussians moves and evaluates a sixteenth of the SH."""
    return dataclasses.replace(data, sh=data.sh[:, :1], extra={}, layout=())


def baked(data: GaussianSplatData, index: np.ndarray, camera: Camera) -> GaussianSplatData:
    """The ``index`` subset of ``data`` with each Gaussian's colour as this camera sees it baked
    into its SH DC (``view_colours``): rendered by this camera (or a crop of it: the same centre)
    it shows the colour of the full SH, to float rounding."""
    sub = data.subset(index)
    return dataclasses.replace(sub, sh=rgb_to_sh_dc(view_colours(sub, camera)).astype(np.float32)[:, None, :],
                               extra={}, layout=())


def to_device(array: np.ndarray) -> jax.Array:
    """A host array on the default device as it is: ``jax.device_put`` copies it, where
    ``jnp.asarray`` compiles a small program for every new shape (JAX 0.10)."""
    return jax.device_put(np.ascontiguousarray(array))


def _features(features: np.ndarray | None, n: int, pad_to: int, num_features: int) -> np.ndarray:
    feats = np.zeros((pad_to, num_features), np.float32)
    if features is not None and n:
        feats[:n, : features.shape[1]] = features
    return feats


def batch_size(pad_to: int, jobs: int) -> int:
    """Crops per launch: at most ``MAX_BATCH`` and ``BATCH_GAUSSIANS`` padded Gaussians, and no
    more than the pass needs (a power of two, so a pass compiles few programs)."""
    return max(1, min(MAX_BATCH, BATCH_GAUSSIANS // pad_to, next_power_of_two(jobs)))


class CropRenderer:
    """Renders Gaussian subsets into crops, every subset of a pass padded to one count.

    ``renders`` counts crops rendered, ``launches`` the renderer calls that rendered them."""

    def __init__(self, renderer: Renderer | None = None):
        self.renderer = renderer or Renderer()
        self.renders = 0
        self.launches = 0
        self._uploaded: tuple | None = None   # (data, SH coefficients, its rows on the device)

    def _on_device(self, data: GaussianSplatData, sh_coeffs: int) -> dict[str, jax.Array]:
        """``data``'s kernel arrays on the device followed by transparent padding rows (from row
        ``data.num``) up to its bucket (one gather program per bucket), kept for the next pass over
        the same ``data`` object."""
        if self._uploaded is None or self._uploaded[0] is not data or self._uploaded[1] != sh_coeffs:
            self._uploaded = None   # the old rows go before the new ones arrive
            rows = padded(data, gaussian_bucket(data.num + 1), sh_coeffs)
            self._uploaded = (data, sh_coeffs, {k: to_device(v) for k, v in rows.items()})
        return self._uploaded[2]

    def _batch(self, jobs: list[CropJob], per: int, pad_to: int, sh_coeffs: int, shared: GaussianSplatData | None
               ) -> Gaussians:
        """The Gaussians of a launch (``per`` rows of ``pad_to``; rows past the jobs' are empty crops):
        subsets of one ``shared`` set gathered on the device from its rows there, else packed on the host."""
        if shared is not None:
            rows = np.full((per, pad_to), shared.num, np.int32)   # the padding row
            for b, j in enumerate(jobs):
                rows[b, :len(j.index)] = j.index
            return Gaussians(**_gather_rows(self._on_device(shared, sh_coeffs), to_device(rows)))
        arrays = _pad_rows(per, pad_to, sh_coeffs)
        for b, j in enumerate(jobs):
            _fill_rows(arrays, b, j.data, j.index)
        return Gaussians(**{k: to_device(v) for k, v in arrays.items()})

    def render(self, data: GaussianSplatData, crop: Crop, pad_to: int, features: np.ndarray | None = None,
               num_features: int = 2, background=None) -> CropImage:
        """The render of ``data`` (≤ ``pad_to`` Gaussians) in the crop. features: (N, F ≤ num_features)."""
        g = Gaussians(**{k: to_device(v) for k, v in padded(data, pad_to).items()})
        bg = None if background is None else np.asarray(background, np.float32)
        self.renders += 1
        self.launches += 1
        out = self.renderer.render(g, crop.camera, features=to_device(_features(features, data.num, pad_to,
                                                                                num_features)), background=bg)
        return CropImage(np.asarray(out.rgb), np.asarray(out.alpha), np.asarray(out.depth), np.asarray(out.features))

    def render_many(self, jobs: list[CropJob], pad_to: int, num_features: int = 2) -> list[CropImage]:
        """Every job's render (crops of one size, each subset ≤ ``pad_to``), ``batch_size`` per launch;
        a short last batch is filled with empty crops. Equal to ``render`` of each job (the batched
        program vmaps the same kernel; ``tests/construct/background/test_views.py``).

        A ``RuntimeError`` of the renderer (its buffers) is raised for the whole batch; callers that
        let one crop fail alone render that batch's jobs one by one (``render``)."""
        if not jobs:
            return []
        sizes = {j.crop.size for j in jobs}
        if len(sizes) != 1:
            raise ValueError(f"render_many: crops of one pass share one size, got {sorted(sizes)}")
        sh_coeffs = max(j.data.sh.shape[1] for j in jobs)
        per = batch_size(pad_to, len(jobs))
        # subsets of one set (the capture's crops) are gathered on the device from one upload
        shared = jobs[0].data if all(j.data is jobs[0].data and j.index is not None for j in jobs) else None
        images: list[CropImage] = []
        for start in range(0, len(jobs), per):
            chunk = jobs[start:start + per]
            empty = dataclasses.replace(chunk[0], index=np.zeros(0, np.int64), features=None)
            batch = chunk + [empty] * (per - len(chunk))
            g = self._batch(chunk, per, pad_to, sh_coeffs, shared)
            feats = np.stack([_features(j.features, j.num, pad_to, num_features) for j in batch])
            bgs = np.stack([np.zeros(3, np.float32) if j.background is None else np.asarray(j.background, np.float32)
                            for j in batch])
            out = self.renderer.render_batch(g, [j.crop.camera for j in batch], features=to_device(feats),
                                             background=to_device(bgs))
            rgb, alpha, depth, features = (np.asarray(x) for x in (out.rgb, out.alpha, out.depth, out.features))
            images += [CropImage(rgb[b], alpha[b], depth[b], features[b]) for b in range(len(chunk))]
            self.renders += len(chunk)
            self.launches += 1
        return images


@jax.jit
def _gather_rows(arrays: dict[str, jax.Array], rows: jax.Array) -> dict[str, jax.Array]:
    """arrays: each (M, ...) kernel array; rows (B, P) int32 → each (B, P, ...)."""
    return {k: v[rows] for k, v in arrays.items()}


def pass_bucket(counts: list[int]) -> int:
    """The padded Gaussian count of a pass: the power-of-two bucket of its largest subset."""
    return gaussian_bucket(max([1, *counts]))
