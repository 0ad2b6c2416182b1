"""Floater rules: a dense surface is kept; a far, isolated centre, a transparent Gaussian and
an outsized one are dropped; the rules do not depend on the scene's units."""

from __future__ import annotations

import numpy as np

from phirie_jax.observe.config import FloaterConfig
from phirie_jax.observe.floaters import floater_mask

SPACING = 0.005  # the dense surface's centre spacing (metres)


def plane(n: int = 60, seed: int = 0):
    """A dense jittered grid of opaque, flat Gaussians on z = 0: means (n², 3), log_scales, logits."""
    rng = np.random.default_rng(seed)
    xy = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), -1).reshape(-1, 2) * SPACING
    means = np.c_[xy + rng.normal(0, 0.1 * SPACING, xy.shape), rng.normal(0, 0.1 * SPACING, len(xy))]
    log_scales = np.log(np.c_[np.full((len(xy), 2), SPACING), np.full(len(xy), 0.1 * SPACING)])
    log_scales += rng.normal(0, 0.2, log_scales.shape)
    return means, log_scales, np.full(len(xy), 3.0)  # opacity 0.95


def with_extras(means, log_scales, logits):
    """The plane plus: a far floater (index n), a transparent one on the plane (n+1), a huge one (n+2)."""
    n = len(means)
    extra_means = np.array([[0.15, 0.15, 0.5], [0.1, 0.1, 0.0], [0.2, 0.1, 0.0]])
    extra_scales = np.log(np.array([[SPACING] * 3, [SPACING] * 3, [1.0, 1.0, 1.0]]))
    extra_logits = np.array([3.0, -6.0, 3.0])  # opacity 0.95, 0.0025, 0.95
    return (np.r_[means, extra_means], np.r_[log_scales, extra_scales], np.r_[logits, extra_logits]), n


def test_dense_surface_is_kept_and_floaters_dropped():
    (means, log_scales, logits), n = with_extras(*plane())
    keep, record = floater_mask(means, log_scales, logits, FloaterConfig())
    assert keep[:n].mean() > 0.995  # a jittered dense plane loses (almost) nothing
    assert not keep[n:].any()
    assert record["dropped_transparent"] == 1 and record["dropped_large"] >= 1 and record["dropped_isolated"] >= 1
    assert record["kept"] == keep.sum()
    assert record["kept"] + record["dropped_transparent"] + record["dropped_large"] + record["dropped_isolated"] \
        == len(means)


def test_rules_are_scale_free():
    (means, log_scales, logits), _ = with_extras(*plane())
    keep, _ = floater_mask(means, log_scales, logits, FloaterConfig())
    for scale in (0.01, 37.0):
        scaled, _ = floater_mask(means * scale, log_scales + np.log(scale), logits, FloaterConfig())
        np.testing.assert_array_equal(scaled, keep)


def test_disabled_keeps_everything():
    (means, log_scales, logits), _ = with_extras(*plane(10))
    keep, record = floater_mask(means, log_scales, logits, FloaterConfig(enabled=False))
    assert keep.all() and record["kept"] == len(means)
