"""3DGS densification on the device: clone, split and prune a padded Gaussian set.

The rules are the reference implementation's (Kerbl et al. 2023) and gsplat's ``DefaultStrategy``,
as ``phirie_jax.capture.densify.densify_and_prune`` states them on the host (the slow reference
these kernels are tested against):

- a valid Gaussian whose mean screen gradient reaches the threshold is chosen, the highest
  gradients first while ``room`` lasts; a chosen one no larger than ``dense_size`` (its largest
  axis) is *cloned*, a larger one *split* into two children offset by a sample of itself with
  scales / ``SPLIT_SHRINK``;
- every Gaussian of the result below ``min_opacity``, and (``prune_large``) above ``max_size``,
  is *pruned*.

The result keeps the host's order: the Gaussians not split (in row order), the clones, the first
children, the second children, the pruned ones left out. Two programs, so that the host learns
the new count (and picks the next bucket) before the arrays of that size are made:

1. ``plan``: which rows go where, the counts; fixed size, one small scalar to read back.
2. ``apply``: scatter the four streams into a fresh padded set of ``size`` rows and gather the
   optimizer's per-Gaussian moments by source row (zeros for the Gaussians densification made).

No temporary holds four copies of the set: each stream is scattered from the input itself.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from kernels.gaussians import Gaussians, quat_to_rotmat
from kernels.pytree import pytree_dataclass
from kernels.splat_fit import PAD_OPACITY_LOGIT

SPLIT_SHRINK = 1.6      # a split Gaussian's children have its scale / this (3DGS)
PAD_LOG_SCALE = -10.0   # padding rows: tiny (and transparent: PAD_OPACITY_LOGIT)
STREAMS = 4             # kept rows, clones, first children, second children


@pytree_dataclass
class DensifyLimits:
    """The thresholds of one densification, in the scene's units (scalars, traced)."""

    grad_threshold: jax.Array  # () mean screen gradient (NDC units) that chooses a Gaussian
    dense_size: jax.Array      # () largest axis up to which a chosen Gaussian is cloned (else split)
    min_opacity: jax.Array     # () pruned below
    max_size: jax.Array        # () pruned above (largest axis), where prune_large
    prune_large: jax.Array     # () bool
    max_gaussians: jax.Array   # () int32: no growth past this count


@pytree_dataclass
class DensifyPlan:
    """Where each row of each stream goes (``size`` = out of range: dropped) and the counts."""

    dest: jax.Array     # (4, S) int32 row in the result, per stream
    count: jax.Array    # () int32 Gaussians in the result
    cloned: jax.Array   # () int32
    split: jax.Array    # () int32
    pruned: jax.Array   # () int32


def children_means(params: Gaussians, noise: jax.Array) -> jax.Array:
    """(2, S, 3) the split children's means: each row's mean + R (noise ⊙ scale).

    noise (2, S, 3) standard normal samples, one per child and row."""
    rot = quat_to_rotmat(params.quats)                       # (S, 3, 3)
    local = noise * jnp.exp(params.log_scales)[None]         # (2, S, 3)
    return params.means[None] + jnp.einsum("sij,csj->csi", rot, local)


def plan(params: Gaussians, valid: jax.Array, grad: jax.Array, limits: DensifyLimits) -> DensifyPlan:
    """The rows densification keeps, adds and prunes (module docstring).

    params: S Gaussians (valid rows first); valid (S,) bool; grad (S,) mean screen gradient."""
    size = valid.shape[0]
    n = jnp.sum(valid, dtype=jnp.int32)
    largest = jnp.max(params.log_scales, axis=1)             # log of the largest axis
    candidate = valid & (grad >= limits.grad_threshold)
    # rank of each candidate by descending gradient (ties: lower row first), as a stable sort
    order = jnp.argsort(jnp.where(candidate, -grad, jnp.inf), stable=True)
    rank = jnp.zeros(size, jnp.int32).at[order].set(jnp.arange(size, dtype=jnp.int32))
    room = jnp.maximum(limits.max_gaussians - n, 0)
    chosen = candidate & (rank < room)
    big = largest > jnp.log(limits.dense_size)
    clone, split = chosen & ~big, chosen & big

    opaque = jax.nn.sigmoid(params.opacity_logits) >= limits.min_opacity
    child_largest = largest - jnp.log(SPLIT_SHRINK)
    small = ~limits.prune_large | (largest <= jnp.log(limits.max_size))
    small_child = ~limits.prune_large | (child_largest <= jnp.log(limits.max_size))
    present = jnp.stack([valid & ~split, clone, split, split])
    alive = jnp.stack([opaque & small, opaque & small, opaque & small_child, opaque & small_child])
    taken = (present & alive).reshape(-1)
    dest = jnp.where(taken, jnp.cumsum(taken, dtype=jnp.int32) - 1, jnp.iinfo(jnp.int32).max)
    return DensifyPlan(dest=dest.reshape(STREAMS, size), count=jnp.sum(taken, dtype=jnp.int32),
                       cloned=jnp.sum(clone, dtype=jnp.int32), split=jnp.sum(split, dtype=jnp.int32),
                       pruned=jnp.sum(present & ~alive, dtype=jnp.int32))


def apply(params: Gaussians, moments: Any, densify_plan: DensifyPlan, noise: jax.Array, size: int
          ) -> tuple[Gaussians, jax.Array, Any]:
    """The densified set padded to ``size`` rows, its valid mask and the moments carried over.

    params: S Gaussians; moments: a pytree whose leaves with S rows are per-Gaussian (Adam's
    moments; other leaves pass through); noise (2, S, 3) the children's samples. ``size`` must
    hold ``densify_plan.count`` rows (static: jit with it static)."""
    rows = params.num
    dest = jnp.where(densify_plan.dest < size, densify_plan.dest, size)  # out of range: dropped
    children = children_means(params, noise)
    child_scales = params.log_scales - jnp.log(SPLIT_SHRINK)

    def scattered(fill, streams):
        out = jnp.full((size,) + streams[0].shape[1:], fill, streams[0].dtype)
        for k, stream in enumerate(streams):
            out = out.at[dest[k]].set(stream, mode="drop")
        return out

    out = Gaussians(
        means=scattered(0.0, [params.means, params.means, children[0], children[1]]),
        quats=scattered(1.0, [params.quats] * STREAMS),
        log_scales=scattered(PAD_LOG_SCALE, [params.log_scales, params.log_scales, child_scales, child_scales]),
        opacity_logits=scattered(PAD_OPACITY_LOGIT, [params.opacity_logits] * STREAMS),
        sh=scattered(0.0, [params.sh] * STREAMS))
    # the source row of each result row: the kept stream's rows keep their moments, the rest start at zero
    source = jnp.full(size, -1, jnp.int32).at[dest[0]].set(jnp.arange(rows, dtype=jnp.int32), mode="drop")

    def carried(x):
        if jnp.ndim(x) == 0 or x.shape[0] != rows:
            return x
        picked = x[jnp.maximum(source, 0)]
        return jnp.where((source >= 0).reshape((-1,) + (1,) * (x.ndim - 1)), picked, jnp.zeros_like(picked))

    valid = jnp.arange(size) < densify_plan.count
    return out, valid, jax.tree.map(carried, moments)
