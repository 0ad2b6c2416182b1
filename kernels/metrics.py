"""Geometry metrics between a placed asset and a reference, with no alignment of any kind.

Both take points sampled on the two surfaces (host side), in the same (scene) frame:

- F1 at τ: precision = fraction of asset points within τ of the reference, recall =
  fraction of reference points within τ of the asset, F1 = 2PR / (P + R). The paper
  reports τ = 20 mm (and 40 mm).
- Symmetric Chamfer distance in cm: the mean of the two mean nearest distances,
  ½ (mean_a min_b ‖a − b‖ + mean_b min_a ‖a − b‖), in centimetres.

Exact nearest neighbours (chunked brute force, ``kernels.chamfer.nearest_sq``).
"""

from __future__ import annotations

import jax.numpy as jnp

from kernels.chamfer import masked_mean, nearest_sq

CM_PER_M = 100.0


def _distances(a, a_mask, b, b_mask, chunk: int):
    """Nearest distances both ways: a (Na, 3), a_mask (Na,) bool, b (Nb, 3), b_mask (Nb,) bool.
    → (Na,) a → B, (Nb,) b → A."""
    d2_ab = nearest_sq(a, b, b_mask, chunk)
    d2_ba = nearest_sq(b, a, a_mask, chunk)
    return jnp.sqrt(d2_ab), jnp.sqrt(d2_ba)


def f1_score(pred, pred_mask, ref, ref_mask, tau, chunk: int = 256):
    """(F1, precision, recall) at threshold tau () metres. pred (Np, 3), pred_mask (Np,) bool,
    ref (Nr, 3), ref_mask (Nr,) bool."""
    d_pr, d_rp = _distances(pred, pred_mask, ref, ref_mask, chunk)
    precision = masked_mean((d_pr <= tau).astype(pred.dtype), pred_mask)
    recall = masked_mean((d_rp <= tau).astype(pred.dtype), ref_mask)
    f1 = 2 * precision * recall / jnp.maximum(precision + recall, 1e-12)
    return f1, precision, recall


def chamfer_cm(pred, pred_mask, ref, ref_mask, chunk: int = 256):
    """Symmetric Chamfer distance in cm: ½ (mean pred→ref + mean ref→pred). pred (Np, 3),
    pred_mask (Np,) bool, ref (Nr, 3), ref_mask (Nr,) bool. → ()."""
    d_pr, d_rp = _distances(pred, pred_mask, ref, ref_mask, chunk)
    return 0.5 * CM_PER_M * (masked_mean(d_pr, pred_mask) + masked_mean(d_rp, ref_mask))


def geometry_metrics(pred, pred_mask, ref, ref_mask, taus=(0.02, 0.04), chunk: int = 256):
    """F1 at each τ and the Chamfer distance from one pair of distance passes.

    pred (Np, 3), pred_mask (Np,) bool, ref (Nr, 3), ref_mask (Nr,) bool, taus (T,) metres.

    → (f1 (T,), precision (T,), recall (T,), chamfer_cm ()).
    """
    d_pr, d_rp = _distances(pred, pred_mask, ref, ref_mask, chunk)
    taus = jnp.asarray(taus, pred.dtype)
    precision = jnp.stack([masked_mean((d_pr <= t).astype(pred.dtype), pred_mask) for t in taus])
    recall = jnp.stack([masked_mean((d_rp <= t).astype(pred.dtype), ref_mask) for t in taus])
    f1 = 2 * precision * recall / jnp.maximum(precision + recall, 1e-12)
    cd = 0.5 * CM_PER_M * (masked_mean(d_pr, pred_mask) + masked_mean(d_rp, ref_mask))
    return f1, precision, recall, cd
