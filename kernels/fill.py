"""Plane-disk fill: new flat Gaussians on a support plane, refined against image targets.

The background branch (``phirie_jax.construct.background.stage``) removes an object's Gaussians
and lays new disks on a grid over the exposed part of the support plane. This kernel fits
those disks — and only them — to inpainted target crops with the splat renderer.

One target *frame* is a crop of one camera. The kept scene is split there, once on the
host (``phirie_jax.construct.background.targets.split_layers``), into three layers:

    front  kept Gaussians in front of the disks: premultiplied colour F, transmittance T_F
    slab   kept Gaussians on the disks' plane (they interleave with the disks in depth): rendered
           with the new disks every step, held fixed (stop_gradient)
    back   kept Gaussians behind the disks, over the background colour: colour B

and the crop is composed as  F + T_F · (S + T_S · B)  with S, T_S the slab render (new disks
included). Outside the disks' depth band the split is by view depth, so those Gaussians sort
exactly as the renderer sorts them; inside it by the height over the disks' plane, which is
the renderer's order up to Gaussians whose centre depth and surface depth disagree. Pixels no disk can reach (``reach``) show the kept
render, so the slab need only hold the band's Gaussians that touch the reachable pixels: a
step renders a few thousand Gaussians instead of the scene.

Loss per frame (3DGS's photometric loss inside the frame's mask): (1 − λ) L1 + λ D-SSIM,
``kernels.image_metrics.masked_l1_dssim``; frames are batched with ``vmap`` and weighted by
their mask area. Parameters of a disk (``FillParams``): SH DC colour, opacity logit, in-plane
offset from its grid cell (bounded by ``max_offset`` through tanh), in-plane log-scales (clipped
to [``min_log_scale``, ``max_log_scale``]). Its orientation (the plane's) and thickness are fixed.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp

from kernels.gaussians import Gaussians, concatenate
from kernels.image_metrics import masked_l1_dssim
from kernels.pytree import pytree_dataclass
from kernels.raster import RasterConfig, rasterize

PAD_OPACITY_LOGIT = -1e4  # padding disks: opacity 0, culled by the projection


@pytree_dataclass
class FillParams:
    """What the refinement optimizes, per disk (N = padded disk count)."""

    dc: jax.Array              # (N, 3) SH degree-0 coefficients
    opacity_logits: jax.Array  # (N,)
    raw_offsets: jax.Array     # (N, 2) in-plane offset = max_offset · tanh(raw)
    log_scales: jax.Array      # (N, 2) in-plane log σ


@pytree_dataclass
class FillGeometry:
    """What stays fixed, per disk."""

    centres: jax.Array        # (N, 3) grid cell centres on the plane
    tangents: jax.Array       # (N, 2, 3) in-plane unit axes (u, v)
    quats: jax.Array          # (N, 4) wxyz rotation with columns (u, v, normal)
    log_thickness: jax.Array  # (N,) log σ along the normal
    valid: jax.Array          # (N,) bool, False for padding
    max_offset: jax.Array     # () metres
    min_log_scale: jax.Array  # ()
    max_log_scale: jax.Array  # ()


@pytree_dataclass
class FillFrame:
    """One target crop (leading B under the batched loss)."""

    K: jax.Array                # (3, 3) crop intrinsics
    world_to_camera: jax.Array  # (4, 4)
    slab: Gaussians             # S kept Gaussians near the plane, SH DC only (colour baked for this view)
    disks: jax.Array            # (D,) int32 the disks that can touch this crop (indices into the params)
    disk_valid: jax.Array       # (D,) bool, False for padding
    front_rgb: jax.Array        # (C, C, 3) premultiplied colour of the front layer
    front_trans: jax.Array      # (C, C) transmittance of the front layer
    back_rgb: jax.Array         # (C, C, 3) back layer over the background colour
    kept_rgb: jax.Array         # (C, C, 3) the kept scene rendered (shown where no disk can reach)
    reach: jax.Array            # (C, C) bool: pixels the disks can touch (the slab holds every kept
                                #   Gaussian of the band that touches them; elsewhere the crop is kept_rgb)
    target: jax.Array           # (C, C, 3)
    mask: jax.Array             # (C, C) loss weights (0 outside the frame's region, and for padding frames)


def fill_gaussians(params: FillParams, geom: FillGeometry) -> Gaussians:
    """The disks as Gaussians (SH degree 0). Works on any subset (a gather of both pytrees)."""
    offsets = geom.max_offset * jnp.tanh(params.raw_offsets)
    means = geom.centres + jnp.einsum("nk,nkd->nd", offsets, geom.tangents)
    log_scales = jnp.concatenate([
        jnp.clip(params.log_scales, geom.min_log_scale, geom.max_log_scale),
        geom.log_thickness[:, None]], axis=1)
    return Gaussians(
        means=means, quats=geom.quats, log_scales=log_scales,
        opacity_logits=jnp.where(geom.valid, params.opacity_logits, PAD_OPACITY_LOGIT),
        sh=params.dc[:, None, :])


def render_frame(params: FillParams, geom: FillGeometry, frame: FillFrame, *, width: int,
                 config: RasterConfig):
    """One frame's composed crop.  Returns rgb (C, C, 3), overflow () bool, needed () int32.

    Only the frame's disks are rendered (a gather: their gradients scatter back into the
    params). The kept slab is wrapped in ``stop_gradient``: gradients reach only the new disks.
    """
    slab = jax.tree.map(jax.lax.stop_gradient, frame.slab)
    take = lambda x: x[frame.disks] if jnp.ndim(x) else x  # noqa: E731 — the frame's disks only
    sub_geom = jax.tree.map(take, geom)
    sub_geom = sub_geom.replace(valid=sub_geom.valid & frame.disk_valid)
    gaussians = concatenate([slab, fill_gaussians(jax.tree.map(take, params), sub_geom)])
    out = rasterize(gaussians, frame.K, frame.world_to_camera, width=width, height=width, config=config)
    layered = out.rgb + (1.0 - out.alpha)[..., None] * frame.back_rgb
    rgb = frame.front_rgb + frame.front_trans[..., None] * layered
    return jnp.where(frame.reach[..., None], rgb, frame.kept_rgb), out.overflow, out.num_intersections


def frame_loss(params: FillParams, geom: FillGeometry, frame: FillFrame, *, width: int,
               config: RasterConfig, dssim_weight: float):
    """() masked (1 − λ) L1 + λ D-SSIM of one frame, and (overflow, needed)."""
    rgb, overflow, needed = render_frame(params, geom, frame, width=width, config=config)
    loss = masked_l1_dssim(rgb, frame.target, frame.mask, dssim_weight)
    return loss, (overflow, needed)


def batched_loss(params: FillParams, geom: FillGeometry, frames: FillFrame, *, width: int,
                 config: RasterConfig, dssim_weight: float):
    """() mask-area-weighted mean of ``frame_loss`` over B frames; aux: per-frame losses (B,),
    overflow () bool, needed () int32 (the most tile intersections any frame needed)."""
    losses, (overflow, needed) = jax.vmap(
        lambda f: frame_loss(params, geom, f, width=width, config=config, dssim_weight=dssim_weight)
    )(frames)
    area = jnp.sum(frames.mask, axis=(1, 2))
    total = jnp.sum(losses * area) / jnp.maximum(jnp.sum(area), 1.0)
    return total, (losses, jnp.any(overflow), jnp.max(needed))


@functools.cache
def optimizer():
    """Adam with unit step (per-field learning rates are applied by ``fill_step``); optax is
    imported here so that ``import kernels`` needs only jax and numpy."""
    import optax

    return optax.chain(optax.scale_by_adam(), optax.scale(-1.0))


def init_state(params: FillParams):
    return optimizer().init(params)


def fill_step(params: FillParams, opt_state: Any, geom: FillGeometry, frames: FillFrame, lrs: FillParams, *,
              width: int, config: RasterConfig, dssim_weight: float):
    """One Adam step on the disks.  lrs: a ``FillParams`` of per-field learning rates (scalars).

    Returns (params, opt_state, loss, aux) — aux as in ``batched_loss``, for the params *before*
    the step. Jit with ``width``, ``config`` and ``dssim_weight`` static.
    """
    (loss, aux), grads = jax.value_and_grad(batched_loss, has_aux=True)(
        params, geom, frames, width=width, config=config, dssim_weight=dssim_weight)
    updates, opt_state = optimizer().update(grads, opt_state, params)
    params = jax.tree.map(lambda p, u, lr: p + lr * u, params, updates, lrs)
    return params, opt_state, loss, aux
