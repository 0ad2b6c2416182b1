"""Degenerate Gaussians: ones a file may hold that no stage can use.

A Gaussian is degenerate when its mean, opacity, scale, quaternion or SH holds a value that is
not finite in float32 (NaN, ±inf, or beyond float32's range: the kernels compute in float32,
where such a value becomes inf), when its quaternion is zero (no rotation: normalising it
gives 0/0), or when a log-scale lies beyond ``MAX_ABS_LOG_SCALE``. ``phirie info`` counts
them; ``load_scene`` drops them with one warning line.
"""

from __future__ import annotations

import numpy as np

from phirie_jax.types import GaussianSplatData

# |log σ| ≤ 20 means 2e-9 ≤ σ ≤ 5e8 in the scene's unit. Trained captures stay well inside
# (about [-15, 5] in any unit from mm to km; the donut test capture spans [-9.7, -3.4]), so the bound
# never touches a real Gaussian; beyond it a Gaussian is far below any pixel or wider than any
# scene: the trace of a diverged optimisation or of a corrupt file.
MAX_ABS_LOG_SCALE = 20.0
# A stored quaternion shorter than this is a zero with rounding noise, not a rotation:
# training starts from unit quaternions and never shrinks one by twelve orders of magnitude.
MIN_QUAT_NORM = 1e-12
FLOAT32_MAX = float(np.finfo(np.float32).max)

# Each degenerate Gaussian is counted once, under the first of these that applies.
REASONS = (
    "non-finite mean",
    "non-finite opacity",
    "non-finite scale",
    "non-finite quaternion",
    "zero quaternion",
    f"|log-scale| > {MAX_ABS_LOG_SCALE:g}",
    "non-finite SH",
)


def _not_finite(values: np.ndarray) -> np.ndarray:
    """(N,) True where any value of a row is NaN, ±inf or beyond float32's range."""
    values = np.asarray(values)
    return ~(np.abs(values.reshape(values.shape[0], -1)) <= FLOAT32_MAX).all(axis=1)  # NaN: False


def _reason_masks(data: GaussianSplatData) -> list[np.ndarray]:
    """One (N,) mask per entry of ``REASONS`` (a Gaussian may be in several)."""
    quats = np.asarray(data.quats, np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        norms = np.linalg.norm(quats, axis=1)
        huge = (np.abs(np.asarray(data.log_scales, np.float64)) > MAX_ABS_LOG_SCALE).any(axis=1)
    return [
        _not_finite(data.means),
        _not_finite(data.opacity_logits),
        _not_finite(data.log_scales),
        _not_finite(data.quats),
        norms < MIN_QUAT_NORM,
        huge,
        _not_finite(data.sh),
    ]


def degenerate_reasons(data: GaussianSplatData) -> np.ndarray:
    """(N,) int index into ``REASONS`` of each Gaussian's first degenerate reason; -1 if sound."""
    out = np.full(data.num, -1, np.int64)
    for index, mask in reversed(list(enumerate(_reason_masks(data)))):
        out[mask] = index
    return out


def degenerate_mask(data: GaussianSplatData) -> np.ndarray:
    """(N,) bool, True for a degenerate Gaussian."""
    return degenerate_reasons(data) >= 0


def degenerate_counts(data: GaussianSplatData) -> dict[str, int]:
    """Reason → number of Gaussians (each counted once, first reason in ``REASONS`` order);
    reasons that no Gaussian has are left out, so a sound set gives ``{}``."""
    counts = np.bincount(degenerate_reasons(data) + 1, minlength=len(REASONS) + 1)[1:]
    return {reason: int(n) for reason, n in zip(REASONS, counts) if n}


def describe_counts(counts: dict[str, int]) -> str:
    """``{"zero quaternion": 3, ...}`` → ``"3 zero quaternion, ..."`` (for a message line)."""
    return ", ".join(f"{n} {reason}" for reason, n in counts.items())
