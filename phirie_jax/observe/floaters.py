"""Floaters and haze: Gaussians left out of the splat-derived surface.

A real capture holds Gaussians that are not surface: near-transparent haze (the optimiser
leaves it where it lowers the photometric loss a little), a few huge blobs that paint the
background or the sky, and small clusters floating in free space in front of the cameras.
Rendered into depth they make spikes and sheets that the TSDF then fuses. Three rules drop
them; each is relative to the scene's own Gaussians, so they hold whatever the units:

1. transparent: opacity below ``min_opacity``;
2. large: the largest axis (in log) is more than ``large_mads`` robust deviations (1.4826 ×
   the median absolute deviation) above the median largest axis;
3. isolated: the distance to the ``neighbours``-th nearest remaining centre is more than
   ``isolated_factor`` × the median of that distance.

A Gaussian is counted under the first rule that drops it.
"""

from __future__ import annotations

import time

import numpy as np

from phirie_jax.observe.config import FloaterConfig
from phirie_jax.types import GaussianSplatData

MAD_TO_SIGMA = 1.4826  # the MAD of a normal distribution times this is its standard deviation


def floater_mask(means: np.ndarray, log_scales: np.ndarray, opacity_logits: np.ndarray,
                 config: FloaterConfig) -> tuple[np.ndarray, dict]:
    """Keep mask (N,) bool of the Gaussians that may be surface, and a record of what was dropped.

    means (N, 3), log_scales (N, 3), opacity_logits (N,) as stored in a 3DGS PLY.
    The record has ``kept``, ``dropped_transparent``, ``dropped_large``, ``dropped_isolated``,
    the thresholds the rules used (``max_extent``, ``max_neighbour_distance``, in scene units)
    and ``seconds``.
    """
    from scipy.spatial import cKDTree

    t0 = time.perf_counter()
    n = len(means)
    keep = np.ones(n, bool)
    record = {"kept": n, "dropped_transparent": 0, "dropped_large": 0, "dropped_isolated": 0,
              "max_extent": None, "max_neighbour_distance": None}
    if not config.enabled or n == 0:
        return keep, {**record, "seconds": 0.0}
    opacity = 1.0 / (1.0 + np.exp(-np.asarray(opacity_logits, np.float64)))
    transparent = opacity < config.min_opacity
    keep &= ~transparent

    largest = np.asarray(log_scales, np.float64).max(1)
    if keep.any():
        centre = np.median(largest[keep])
        spread = MAD_TO_SIGMA * np.median(np.abs(largest[keep] - centre))
        limit = centre + config.large_mads * max(spread, 1e-6)
        large = keep & (largest > limit)
        keep &= ~large
        record["max_extent"] = float(np.exp(limit))
    else:
        large = np.zeros(n, bool)

    isolated = np.zeros(n, bool)
    idx = np.flatnonzero(keep)
    if len(idx) > config.neighbours:
        points = np.asarray(means, np.float64)[idx]
        dist, _ = cKDTree(points).query(points, k=config.neighbours + 1, workers=-1)  # the first is the point itself
        kth = dist[:, -1]
        limit = config.isolated_factor * np.median(kth)
        isolated[idx[kth > limit]] = True
        keep &= ~isolated
        record["max_neighbour_distance"] = float(limit)
    record.update(kept=int(keep.sum()), dropped_transparent=int(transparent.sum()), dropped_large=int(large.sum()),
                  dropped_isolated=int(isolated.sum()), seconds=round(time.perf_counter() - t0, 4))
    return keep, record


def surface_gaussians(gaussians: GaussianSplatData, config: FloaterConfig) -> tuple[GaussianSplatData, dict]:
    """The Gaussians that may be surface (``floater_mask``) and the record."""
    keep, record = floater_mask(gaussians.means, gaussians.log_scales, gaussians.opacity_logits, config)
    return (gaussians if keep.all() else gaussians.subset(keep)), record
