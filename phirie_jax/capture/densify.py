"""Between 3DGS training steps: clone, split, prune, reset opacities, pad to buckets.

The rules are those of the reference implementation (Kerbl et al. 2023) and gsplat's
``DefaultStrategy``:

- a Gaussian whose mean screen-space gradient reaches ``grad_threshold`` is *cloned* (an
  identical copy is added) when its largest axis is at most ``percent_dense`` × the scene
  extent, else *split*: it is replaced by two children drawn from it (offset by a sample of
  itself, scales / 1.6); the highest gradients go first when ``max_gaussians`` leaves room for
  fewer;
- then Gaussians below ``min_opacity``, and (``prune_large``) those whose largest axis exceeds
  ``max_scale`` × the extent, are *pruned*;
- an *opacity reset* clamps every opacity to a small ceiling and zeroes its Adam moments, so
  Gaussians that are not needed fade and are pruned.

Gaussians that densification creates start with zero Adam moments; the others keep theirs.
Training densifies on the device (``densify_on_device``: ``kernels.densify``'s two programs, one
count read back); ``densify_and_prune`` states the same rules on the host, in NumPy, and is the
reference the kernels are tested against. Arrays live on the device padded to power-of-two
buckets (``phirie_jax.render.gaussian_bucket``) with transparent padding and a ``valid`` mask,
so a training compiles a handful of programs.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, Protocol

import jax
import jax.numpy as jnp
import numpy as np

from kernels import densify as densify_kernels
from kernels import splat_fit
from kernels.densify import PAD_LOG_SCALE, SPLIT_SHRINK, DensifyLimits
from kernels.gaussians import Gaussians
from phirie_jax.capture.programs import Programs, direct, like, with_rows
from phirie_jax.geometry import sigmoid
from phirie_jax.render import gaussian_bucket
from phirie_jax.types import GaussianSplatData


class DensifyRule(Protocol):
    """The thresholds densification reads (``TrainConfig`` and the synthetic ``FitConfig`` have them)."""

    grad_threshold: float   # mean screen-space gradient (NDC units) that densifies
    percent_dense: float    # × extent: larger Gaussians are split, smaller ones cloned
    min_opacity: float      # pruned below
    max_scale: float        # × extent: pruned above (largest axis)
    max_gaussians: int      # no growth past this count


def quat_matrices(q: np.ndarray) -> np.ndarray:
    """(N, 4) wxyz, any length → (N, 3, 3) rotations."""
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=1).reshape(-1, 3, 3)


def densify_and_prune(data: GaussianSplatData, grad: np.ndarray, extent: float, rule: DensifyRule,
                      noise: np.ndarray, densify: bool = True, prune_large: bool = True
                      ) -> tuple[GaussianSplatData, np.ndarray, dict]:
    """Clone, split and prune (module docstring), on the host. grad (N,) mean screen gradient of
    each Gaussian; noise (2, N, 3) standard normal samples: child k of a split row i is offset
    by R_i (noise[k, i] ⊙ scale_i).

    Returns the new set, the source row (M,) of each new Gaussian in ``data`` (−1 for the Gaussians
    densification created: their Adam moments start at zero, as in 3DGS) and the counts."""
    n = data.num
    largest = np.exp(data.log_scales.max(axis=1))
    chosen = np.zeros(n, bool)
    if densify:
        room = max(0, rule.max_gaussians - n)  # clone and split both add one Gaussian net
        candidates = np.flatnonzero(grad >= rule.grad_threshold)
        candidates = candidates[np.argsort(-grad[candidates], kind="stable")][:room]
        chosen[candidates] = True
    big = largest > rule.percent_dense * extent
    clone, split = chosen & ~big, chosen & big

    parts, sources = [data.subset(~split)], [np.flatnonzero(~split)]
    parts.append(data.subset(clone))
    sources.append(np.full(int(clone.sum()), -1))
    if split.any():
        parent = data.subset(split)
        rot = quat_matrices(parent.quats.astype(np.float64))
        for k in range(2):
            local = np.asarray(noise[k], np.float64)[split] * np.exp(parent.log_scales)
            child = dataclasses.replace(parent, means=(parent.means + np.einsum("nij,nj->ni", rot, local)).astype(
                np.float32), log_scales=(parent.log_scales - np.log(SPLIT_SHRINK)).astype(np.float32))
            parts.append(child)
            sources.append(np.full(parent.num, -1))
    grown = GaussianSplatData.join(parts)
    source = np.concatenate(sources)
    alive = sigmoid(grown.opacity_logits) >= rule.min_opacity
    if prune_large:
        alive &= np.exp(grown.log_scales.max(axis=1)) <= rule.max_scale * extent
    counts = {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned": int((~alive).sum())}
    return grown.subset(alive), source[alive], counts


def densify_limits(rule: DensifyRule, extent: float, prune_large: bool) -> DensifyLimits:
    """The rule's thresholds in the scene's units, as ``kernels.densify`` reads them."""
    return DensifyLimits(grad_threshold=jnp.float32(rule.grad_threshold),
                         dense_size=jnp.float32(rule.percent_dense * extent), min_opacity=jnp.float32(rule.min_opacity),
                         max_size=jnp.float32(rule.max_scale * extent), prune_large=jnp.bool_(prune_large),
                         max_gaussians=jnp.int32(rule.max_gaussians))


@jax.jit
def _plan(params: Gaussians, valid, grad_sum, seen, limits: DensifyLimits):
    return densify_kernels.plan(params, valid, grad_sum / jnp.maximum(seen, 1.0), limits)


def children_noise(key, rows: int) -> jax.Array:
    """(2, rows, 3) the split children's standard normal samples, from a JAX key."""
    return jax.random.normal(key, (2, rows, 3), jnp.float32)


@functools.partial(jax.jit, static_argnames="size")
def _apply(params: Gaussians, state, plan, key, *, size: int):
    return densify_kernels.apply(params, state, plan, children_noise(key, params.num), size)


def prepare_densify(programs: Programs, params: Any, state: Any, rows: int, rule: DensifyRule) -> None:
    """Have ``programs`` compile, in the background, densification at ``rows`` rows: the plan, and
    the scatter into the same bucket and into the next. params, state: a step's (any rows)."""
    if not programs.enabled:  # nothing to trace the shapes for
        return
    params, state = with_rows(params, rows), with_rows(state, rows)
    vector = jax.ShapeDtypeStruct((rows,), jnp.float32)
    limits = like(densify_limits(rule, 1.0, True))
    valid = jax.ShapeDtypeStruct((rows,), jnp.bool_)
    programs.prepare(("plan", rows), _plan, (params, valid, vector, vector, limits))
    plan = jax.eval_shape(_plan, params, valid, vector, vector, limits)
    for size in (rows, 2 * rows):
        programs.prepare(("apply", rows, size), _apply, (params, state, plan, like(jax.random.key(0))), size=size)


def densify_on_device(params: Gaussians, valid: jax.Array, state: Any, grad_sum: jax.Array, seen: jax.Array,
                      extent: float, rule: DensifyRule, key, prune_large: bool = True, programs: Callable = direct
                      ) -> tuple[Gaussians, jax.Array, Any, dict]:
    """``densify_and_prune`` on the padded device set (noise from ``key``: ``children_noise``).

    params (S rows, valid first), valid (S,), state (the optimizer's, per-Gaussian leaves of S
    rows), grad_sum (S,) and seen (S,) the screen gradients summed since the last densification
    and the views each Gaussian was seen in. Returns the set padded to the bucket of its new
    count, its valid mask, the state carried over and the counts (the new count, cloned, split,
    pruned). programs: runs the two programs (``phirie_jax.capture.programs``: prepared ones)."""
    plan = programs(("plan", params.num), _plan, params, valid, grad_sum, seen,
                    densify_limits(rule, extent, prune_large))
    count, cloned, split, pruned = (int(x) for x in jax.device_get((plan.count, plan.cloned, plan.split,
                                                                      plan.pruned)))
    size = gaussian_bucket(count)
    params, valid, state = programs(("apply", params.num, size), _apply, params, state, plan, key, size=size)
    return params, valid, state, {"count": count, "cloned": cloned, "split": split, "pruned": pruned}


def padded(data: GaussianSplatData, size: int) -> tuple[Gaussians, jax.Array]:
    """The set padded to ``size`` rows (transparent padding) and its valid mask (size,)."""
    pad = size - data.num

    def cat(x, fill):
        return jnp.asarray(np.concatenate([x, np.full((pad,) + x.shape[1:], fill, np.float32)]), jnp.float32)

    g = Gaussians(means=cat(data.means, 0.0), quats=cat(data.quats, 1.0), log_scales=cat(data.log_scales, PAD_LOG_SCALE),
                  opacity_logits=cat(data.opacity_logits, splat_fit.PAD_OPACITY_LOGIT), sh=cat(data.sh, 0.0))
    return g, jnp.asarray(np.arange(size) < data.num)


def reset_opacity(params: Gaussians, state: Any, ceiling: float) -> tuple[Gaussians, Any]:
    """Opacities clamped to ``ceiling`` (an opacity, not a logit) and their Adam moments zeroed.

    ``state`` is ``kernels.splat_fit.optimizer()``'s: (Adam's state, the scale's)."""
    logit = float(np.log(ceiling / (1.0 - ceiling)))
    adam, *rest = state

    def zeroed(moments: Gaussians) -> Gaussians:
        return moments.replace(opacity_logits=jnp.zeros_like(moments.opacity_logits))

    adam = adam._replace(mu=zeroed(adam.mu), nu=zeroed(adam.nu))
    return params.replace(opacity_logits=jnp.minimum(params.opacity_logits, logit)), (adam, *rest)


def unpadded(params: Gaussians, valid: jax.Array) -> GaussianSplatData:
    """The valid rows of a padded set (valid rows come first), on the host."""
    n = int(valid.sum())
    # whole arrays to the host, then sliced there: a device slice would compile a program per count
    return GaussianSplatData.from_kernel(jax.tree.map(lambda x: np.asarray(x)[:n], params))
