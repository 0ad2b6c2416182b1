"""Host-side rendering: ``Camera`` records in, images out.

The kernel (``kernels.raster.rasterize``) has static shapes: a Gaussian count and a
tile-intersection capacity. This module picks them:

- Gaussian counts are padded to power-of-two buckets (at least ``MIN_GAUSSIAN_BUCKET``)
  with fully transparent Gaussians: opacity logit −1e4, i.e. opacity 0 < 1/255, which
  the projection culls, so padding takes no intersection slot and never contributes.
- The capacity starts at the last one that fitted this (bucket, image size) — else
  the larger of ``initial_capacity`` and 4 per (padded) Gaussian — and when the kernel reports overflow the render is repeated
  with ``room_for`` what it said it needed (an eighth to spare, a quarter octave). Nothing is dropped.
- Programs are jitted once per (bucket, image size, capacity): a second scene of the
  same bucket reuses the compiled program (``TRACE_COUNTS`` counts traces).

``render`` needs concrete values to decide on a retry, so it is not for use inside
``jax.grad``/``jit``; to differentiate, get a fitted config with ``Renderer.fitted_config``
and call ``kernels.raster.rasterize`` in your own jitted loss, checking ``overflow``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from kernels.gaussians import Gaussians
from kernels.raster import RasterConfig, RasterOutput, rasterize
from kernels.raster import render_batch as _kernel_render_batch
from phirie_jax.types import Camera

MIN_GAUSSIAN_BUCKET = 256
PAD_OPACITY_LOGIT = -1e4   # sigmoid → 0: culled by the projection (opacity < 1/255)
INITIAL_CAPACITY = 1 << 16
INTERSECTIONS_GUESS = 4    # first capacity ≥ this many tile intersections per Gaussian
MAX_CAPACITY = 1 << 28     # 2 GiB of int32 sort buffers; beyond this we refuse, loudly

TRACE_COUNTS = {"render": 0, "render_batch": 0}


def _traced_render(gaussians, K, world_to_camera, background, features, *, width, height, config):
    TRACE_COUNTS["render"] += 1  # runs only while jax traces, i.e. once per compiled program
    return rasterize(gaussians, K, world_to_camera, width=width, height=height,
                     background=background, features=features, config=config)


def _traced_render_batch(gaussians, Ks, world_to_cameras, background, features, *, width,
                         height, config):
    TRACE_COUNTS["render_batch"] += 1
    return _kernel_render_batch(gaussians, Ks, world_to_cameras, width=width, height=height,
                                background=background, features=features, config=config)


_STATIC = ("width", "height", "config")
_render_jit = jax.jit(_traced_render, static_argnames=_STATIC)
_render_batch_jit = jax.jit(_traced_render_batch, static_argnames=_STATIC)


def next_power_of_two(n: int) -> int:
    return 1 << max(0, int(n) - 1).bit_length()


def quarter_octave(n: int) -> int:
    """The smallest 2^k × (1, 1.25, 1.5 or 1.75) at least n: a buffer size that wastes at most a
    fifth of its slots (a power of two: up to half), with four programs per doubling."""
    n = max(1, int(n))
    top = next_power_of_two(n)
    if top < 8:
        return top
    return next(top // 8 * m for m in (5, 6, 7, 8) if top // 8 * m >= n)  # n > top / 2 = top // 8 * 4


def room_for(needed: int, spare: int = 8) -> int:
    """Slots for ``needed`` tile intersections with a ``spare``-th more (an eighth by default) for
    the next render, rounded up to a quarter octave. Every binning step (the marks, the slot
    gathers, the sort by tile) walks the whole buffer: a 1080p render of 1.4M Gaussians ran 0.86–0.89×
    gsplat's forward in this size against 1.03–1.09× in the next power of two
    (``experiments/results/bench_render_h100_capacity_rule.json``)."""
    needed = max(1, int(needed))
    return quarter_octave(needed + needed // spare)


def grown_capacity(raster: RasterConfig, needed: int, advice: str) -> RasterConfig:
    """``raster`` with room for ``needed`` tile intersections (at least twice its capacity, a power
    of two); past ``MAX_CAPACITY`` a ``RuntimeError`` ending with ``advice``."""
    capacity = max(2 * raster.capacity, next_power_of_two(needed))
    if capacity > MAX_CAPACITY:
        raise RuntimeError(f"{needed} tile intersections needed, more than the renderer's maximum "
                           f"{MAX_CAPACITY}: {advice}")
    return dataclasses.replace(raster, capacity=capacity)


def gaussian_bucket(n: int) -> int:
    """Padded Gaussian count for n Gaussians."""
    return max(MIN_GAUSSIAN_BUCKET, next_power_of_two(n))


def pad_gaussians(gaussians: Gaussians, size: int) -> Gaussians:
    """Append transparent Gaussians along the Gaussian axis (−2 for means) up to ``size``."""
    n = gaussians.num
    if size < n:
        raise ValueError(f"cannot pad {n} Gaussians down to {size}")
    extra = size - n
    if extra == 0:  # nothing to append: no program (each shape of the appending compiles one)
        return gaussians

    def pad(x, axis, value=0.0):
        xp = np if isinstance(x, np.ndarray) else jnp  # host arrays padded on the host: no program
        shape = list(x.shape)
        shape[axis] = extra
        return xp.concatenate([x, xp.full(shape, value, x.dtype)], axis=axis)

    nd = gaussians.means.ndim  # 2, or 3 with a leading batch dimension
    return Gaussians(
        means=pad(gaussians.means, nd - 2),
        quats=pad(gaussians.quats, nd - 2, 1.0),  # (1, 1, 1, 1): a valid, normalizable quaternion
        log_scales=pad(gaussians.log_scales, nd - 2, -10.0),
        opacity_logits=pad(gaussians.opacity_logits, nd - 2, PAD_OPACITY_LOGIT),
        sh=pad(gaussians.sh, nd - 2),
    )


def prepared(gaussians: Gaussians) -> Gaussians:
    """The set padded to its bucket (``gaussian_bucket``) and on the device, for rendering it
    from many cameras: each render of it then moves and pads nothing. Its renders' ``radii``
    cover the padded set (the padding's are 0)."""
    return jax.device_put(pad_gaussians(gaussians, gaussian_bucket(gaussians.num)))


def camera_arrays(camera: Camera, width: int | None = None, dtype=np.float32):
    """K (3, 3), world_to_camera (4, 4) and the image size, optionally resized.

    ``width``: render at this width; K is scaled by width / camera.width (pixel-centre
    convention kept, ``Camera.scaled``) and the height follows. The renderer is pinhole:
    ``camera.distortion`` is not applied.
    """
    if width is not None and width != camera.width:
        camera = camera.scaled(width / camera.width)
    return (np.asarray(camera.K, dtype), np.asarray(camera.world_to_camera, dtype),
            int(camera.width), int(camera.height))


def _pad_features(features, bucket, dtype):
    """(..., N, F) → (..., bucket, F) with zeros (N ≤ bucket: a prepared set's features may be
    fewer than its Gaussians); None → (bucket, 0). Always an array, so renders with and without
    features of one bucket share the program's signature. Host features are padded on the host."""
    if features is None:
        return jnp.zeros((bucket, 0), dtype)
    xp = np if isinstance(features, np.ndarray) else jnp
    features = xp.asarray(features, dtype)
    if features.shape[-2] != bucket:
        pad_shape = features.shape[:-2] + (bucket - features.shape[-2], features.shape[-1])
        features = xp.concatenate([features, xp.zeros(pad_shape, dtype)], axis=-2)
    return jnp.asarray(features)


def _background(background, dtype):
    """None → black; always an array (one program signature)."""
    return jnp.zeros(3, dtype) if background is None else jnp.asarray(background, dtype)


class Renderer:
    """Renders with capacity buckets, retry on overflow and a memory of what fitted.

    config: the kernel settings (its ``capacity`` and ``tile_capacity`` are managed here).
    The first capacity tried for a new bucket is the larger power of two of
    ``initial_capacity`` and ``per_gaussian_guess`` × the padded Gaussian count.
    """

    def __init__(self, config: RasterConfig = RasterConfig(),
                 initial_capacity: int = INITIAL_CAPACITY, max_capacity: int = MAX_CAPACITY,
                 per_gaussian_guess: int = INTERSECTIONS_GUESS):
        self.config = config
        self.initial_capacity = next_power_of_two(initial_capacity)
        self.per_gaussian_guess = per_gaussian_guess
        self.max_capacity = max_capacity
        self.retries = 0  # renders repeated because a capacity was too small
        self.last_config: RasterConfig | None = None  # what the last render ran with
        self._fitted: dict[tuple, RasterConfig] = {}

    def _run(self, key, call, bucket: int) -> tuple[RasterOutput, RasterConfig]:
        config = self._fitted.get(key) or dataclasses.replace(
            self.config, capacity=max(self.initial_capacity,
                                      next_power_of_two(self.per_gaussian_guess * bucket)))
        while True:
            out = call(config)
            if not bool(np.any(np.asarray(out.overflow))):
                self._fitted[key] = config
                return out, config
            self.retries += 1
            needed = int(np.max(np.asarray(out.num_intersections)))
            longest = int(np.max(np.asarray(out.max_tile_intersections)))
            capacity = max(config.capacity, room_for(needed))
            tile_capacity = config.tile_capacity
            if config.backward == "autodiff" and needed <= config.capacity:
                tile_capacity = max(tile_capacity, next_power_of_two(longest + 1))
            if capacity > self.max_capacity:
                raise RuntimeError(
                    f"the scene needs {needed} tile intersections, more than the renderer's "
                    f"maximum capacity {self.max_capacity}: render at a lower resolution, "
                    "with fewer or smaller Gaussians, or raise max_capacity")
            config = dataclasses.replace(config, capacity=capacity, tile_capacity=tile_capacity)

    def render(self, gaussians: Gaussians, camera: Camera, *, background=None, features=None,
               width: int | None = None) -> RasterOutput:
        """One camera.  gaussians: N Gaussians; features: None or (N, F); background (3,).

        Returns the kernel's ``RasterOutput`` (rgb (H, W, 3), depth, alpha, features,
        radii (N,), diagnostics; ``capacity`` is the bucket that was used).
        """
        n = gaussians.num
        bucket = gaussian_bucket(n)
        dtype = jnp.asarray(gaussians.means).dtype
        K, w2c, w, h = camera_arrays(camera, width, dtype)
        padded = pad_gaussians(gaussians, bucket)
        features = _pad_features(features, bucket, dtype)
        bg = _background(background, dtype)
        key = ("render", bucket, w, h, features.shape[-1])
        out, config = self._run(key, lambda cfg: _render_jit(padded, K, w2c, bg, features,
                                                             width=w, height=h, config=cfg),
                                bucket)
        self.last_config = config
        return out.replace(radii=out.radii[:n])

    def render_batch(self, gaussians: Gaussians | Sequence[Gaussians], cameras: Sequence[Camera],
                     *, background=None, features=None, width: int | None = None) -> RasterOutput:
        """B cameras in one call.  gaussians: one set for all cameras, or B sets of equal
        size (a sequence, or one ``Gaussians`` with a leading B); features: None, (N, F)
        or (B, N, F); background: None, (3,) or (B, 3). Every camera must give the same
        image size (after ``width``). Fields of the result have a leading B.
        """
        if not isinstance(gaussians, Gaussians):
            gaussians = jax.tree.map(lambda *x: jnp.stack([jnp.asarray(v) for v in x]), *gaussians)
        n = gaussians.num
        bucket = gaussian_bucket(n)
        dtype = jnp.asarray(gaussians.means).dtype
        arrays = [camera_arrays(c, width, dtype) for c in cameras]
        sizes = {(a[2], a[3]) for a in arrays}
        if len(sizes) != 1:
            raise ValueError(f"render_batch: cameras give different image sizes {sorted(sizes)}; "
                             "pass width= or group the cameras by size")
        (w, h), = sizes
        Ks = jnp.asarray(np.stack([a[0] for a in arrays]))
        w2cs = jnp.asarray(np.stack([a[1] for a in arrays]))
        padded = pad_gaussians(gaussians, bucket)
        features = _pad_features(features, bucket, dtype)
        bg = _background(background, dtype)
        key = ("batch", bucket, w, h, len(cameras), gaussians.means.ndim, features.shape,
               bg.shape)
        out, config = self._run(key, lambda cfg: _render_batch_jit(
            padded, Ks, w2cs, bg, features, width=w, height=h, config=cfg), bucket)
        self.last_config = config
        return out.replace(radii=out.radii[..., :n])

    def fitted_config(self, gaussians: Gaussians, camera: Camera, *, width: int | None = None
                      ) -> RasterConfig:
        """A config whose capacities hold this scene in this camera (renders once to find it)."""
        self.render(gaussians, camera, width=width)
        return self.last_config


_DEFAULT = Renderer()


def render(gaussians: Gaussians, camera: Camera, *, background=None, features=None,
           width: int | None = None) -> RasterOutput:
    """Render with the module's shared ``Renderer`` (see ``Renderer.render``)."""
    return _DEFAULT.render(gaussians, camera, background=background, features=features,
                           width=width)


def render_batch(gaussians, cameras: Sequence[Camera], *, background=None, features=None,
                 width: int | None = None) -> RasterOutput:
    """Render many cameras with the module's shared ``Renderer`` (see ``Renderer.render_batch``)."""
    return _DEFAULT.render_batch(gaussians, cameras, background=background, features=features,
                                 width=width)
