"""One step of 3DGS training: render a training view, photometric loss, Adam, densification statistics.

This is the optimization a user's 3DGS trainer runs (Kerbl et al. 2023), for one view per step:

    loss = (1 − λ) L1 + λ (1 − SSIM),  λ = 0.2

Adam updates every Gaussian parameter with its own learning rate (``lrs``, a ``Gaussians`` of
scalars or broadcastable arrays; the host decays the position rate). SH bands are switched on
progressively through ``sh_mask``: coefficients of bands not yet on are zeroed before rendering,
so they get no gradient and stay as they are.

Densification needs each Gaussian's view-space positional gradient, in NDC units (× W/2, × H/2)
like the reference implementation, so thresholds do not depend on the image size. Two ways:

- ``exact_screen_gradient``: the gradient at the projected mean itself, dL/d means2d, taken
  through a zero offset added to the projected means (``rasterize``'s ``means2d_offset``), as
  gsplat's ``DefaultStrategy`` reads it;
- otherwise it is recovered from the world gradient g of the mean: a one-pixel move on screen is
  a move of z / f in the camera's x–y plane, hence dL/du ≈ (z / fx) (R g)_x,
  dL/dv ≈ (z / fy) (R g)_y (the paths through depth, covariance and view direction are
  left out). The synthetic scenes' fits (``phirie synth --fitted``) were made this way.

Training images may be float (H, W, 3) in [0, 1] or uint8 (a quarter of the device memory).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp

from kernels.gaussians import Gaussians
from kernels.image_metrics import ssim
from kernels.raster import RasterConfig, intersections_needed, rasterize

PAD_OPACITY_LOGIT = -1e4  # padding Gaussians: opacity 0, culled by the projection


@functools.cache
def optimizer():
    """Adam with unit step (per-field rates are applied by ``train_step``); optax is imported here
    so that ``import kernels`` needs only jax and numpy."""
    import optax

    return optax.chain(optax.scale_by_adam(eps=1e-15), optax.scale(-1.0))


def init_state(params: Gaussians):
    return optimizer().init(params)


def photometric_loss(rendered: jax.Array, target: jax.Array, dssim_weight: float) -> jax.Array:
    """() (1 − λ) mean |rendered − target| + λ (1 − SSIM). rendered (H, W, 3); target (H, W, 3)."""
    l1 = jnp.mean(jnp.abs(rendered - target))
    return (1.0 - dssim_weight) * l1 + dssim_weight * (1.0 - ssim(rendered, target))


def masked_sh(params: Gaussians, valid: jax.Array, sh_mask: jax.Array) -> Gaussians:
    """The Gaussians as rendered: SH bands not yet on zeroed, padding transparent.

    valid (N,) bool; sh_mask (K, 1) 1 for the coefficients of bands that are on, else 0."""
    return params.replace(sh=params.sh * sh_mask,
                          opacity_logits=jnp.where(valid, params.opacity_logits, PAD_OPACITY_LOGIT))


def view_loss(params: Gaussians, valid: jax.Array, sh_mask: jax.Array, K: jax.Array,
              world_to_camera: jax.Array, background: jax.Array, target: jax.Array,
              means2d_offset: jax.Array | None = None, *, config: RasterConfig, dssim_weight: float):
    """() photometric loss of one view; aux (radii (N,), overflow () bool, needed () int32).

    valid (N,); sh_mask (K, 1); K (3, 3); world_to_camera (4, 4); background (3,); target (H, W, 3);
    means2d_offset (N, 2) or None (``rasterize``)."""
    height, width = target.shape[0], target.shape[1]
    out = rasterize(masked_sh(params, valid, sh_mask), K, world_to_camera, width=width, height=height,
                    background=background, config=dataclasses.replace(config, depth=False),  # colour only
                    means2d_offset=means2d_offset)
    return photometric_loss(out.rgb, target, dssim_weight), (out.radii, out.overflow, out.num_intersections)


def as_float_image(image: jax.Array) -> jax.Array:
    """image (H, W, 3) uint8 → float32 in [0, 1]; a float image is returned as it is."""
    if image.dtype == jnp.uint8:
        return image.astype(jnp.float32) / 255.0
    return image


def screen_gradient(grad_means: jax.Array, means: jax.Array, K: jax.Array, world_to_camera: jax.Array,
                    width: int, height: int) -> jax.Array:
    """(N,) norm of the view-space positional gradient in NDC units (see the module docstring).

    grad_means (N, 3) dL/d mean; means (N, 3); K (3, 3); world_to_camera (4, 4)."""
    rot, trans = world_to_camera[:3, :3], world_to_camera[:3, 3]
    z = means @ rot[2] + trans[2]                  # (N,) view depth
    g_cam = grad_means @ rot.T                     # (N, 3) the gradient in camera axes
    du = z / K[0, 0] * g_cam[:, 0] * (0.5 * width)
    dv = z / K[1, 1] * g_cam[:, 1] * (0.5 * height)
    return jnp.sqrt(du * du + dv * dv)


def train_step(params: Gaussians, opt_state: Any, lrs: Gaussians, valid: jax.Array, sh_mask: jax.Array,
               K: jax.Array, world_to_camera: jax.Array, image: jax.Array, background: jax.Array,
               grad_sum: jax.Array, seen: jax.Array, *, config: RasterConfig, dssim_weight: float,
               exact_screen_gradient: bool = False):
    """One Adam step on one training view.

    params: N Gaussians (padding included); lrs: a ``Gaussians`` of per-field learning rates;
    valid (N,) bool; sh_mask (K, 1); K (3, 3); world_to_camera (4, 4); image (H, W, 3) float in
    [0, 1] or uint8 (the view's photo: the caller may keep its photos on the host and pass one
    per step); background (3,); grad_sum (N,) and seen (N,) the densification statistics so far
    (summed screen gradient, number of views a Gaussian was visible in).

    Returns (params, opt_state, loss, grad_sum, seen, radii (N,), overflow, needed); the loss and
    the diagnostics are of the params *before* the step. Jit with ``config``, ``dssim_weight`` and
    ``exact_screen_gradient`` static. A step that overflowed changes nothing (its gradient is
    incomplete): params, opt_state, grad_sum and seen come back as they went in, and the caller
    repeats the step with a larger capacity (so the inputs may be donated).
    """
    target = as_float_image(image)
    height, width = target.shape[0], target.shape[1]
    if exact_screen_gradient:
        offset = jnp.zeros((params.num, 2), params.means.dtype)
        (loss, (radii, overflow, needed)), (grads, g_screen) = jax.value_and_grad(
            view_loss, argnums=(0, 7), has_aux=True)(params, valid, sh_mask, K, world_to_camera, background, target,
                                                     offset, config=config, dssim_weight=dssim_weight)
        g2 = jnp.hypot(g_screen[:, 0] * (0.5 * width), g_screen[:, 1] * (0.5 * height))
    else:
        (loss, (radii, overflow, needed)), grads = jax.value_and_grad(view_loss, has_aux=True)(
            params, valid, sh_mask, K, world_to_camera, background, target, config=config,
            dssim_weight=dssim_weight)
        g2 = screen_gradient(grads.means, params.means, K, world_to_camera, width, height)
    updates, new_state = optimizer().update(grads, opt_state, params)
    new_params = jax.tree.map(lambda p, u, lr: p + lr * u, params, updates, lrs)
    visible = (radii > 0) & valid
    new_sum = grad_sum + jnp.where(visible, g2, 0.0)
    new_seen = seen + visible.astype(seen.dtype)

    def kept(new, old):  # an overflowed step leaves everything as it was
        return jax.tree.map(lambda a, b: jnp.where(overflow, b, a), new, old)

    params, opt_state, grad_sum, seen = kept((new_params, new_state, new_sum, new_seen),
                                             (params, opt_state, grad_sum, seen))
    return params, opt_state, loss, grad_sum, seen, radii, overflow, needed


def views_intersections(params: Gaussians, valid: jax.Array, Ks: jax.Array, world_to_cameras: jax.Array, *,
                        width: int, height: int, config: RasterConfig) -> jax.Array:
    """(V,) int32 tile intersections a step on each view needs (the buffer capacity it must
    have), from the projection alone. valid (N,); Ks (V, 3, 3); world_to_cameras (V, 4, 4)."""
    g = masked_sh(params, valid, jnp.ones((params.sh.shape[1], 1), params.sh.dtype))
    return jax.lax.map(lambda view: intersections_needed(g, view[0], view[1], width=width, height=height,
                                                         config=config), (Ks, world_to_cameras))


def render_views(params: Gaussians, valid: jax.Array, Ks: jax.Array, world_to_cameras: jax.Array,
                 background: jax.Array, *, width: int, height: int, config: RasterConfig):
    """All V views with every SH band on. Returns rgb (V, H, W, 3) and overflow () bool.

    valid (N,); Ks (V, 3, 3); world_to_cameras (V, 4, 4); background (3,)."""
    g = masked_sh(params, valid, jnp.ones((params.sh.shape[1], 1), params.sh.dtype))
    out = jax.lax.map(lambda kw: rasterize(g, kw[0], kw[1], width=width, height=height, background=background,
                                           config=config), (Ks, world_to_cameras))
    return out.rgb, jnp.any(out.overflow)
