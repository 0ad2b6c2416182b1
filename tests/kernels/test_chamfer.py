"""Nearest neighbours and the clipped Chamfer score against SciPy / NumPy references, and
their properties (symmetry, padding, invariance)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import cKDTree

from kernels.chamfer import (
    FAR,
    build_grid,
    clipped_chamfer,
    clipped_distance,
    nearest_grid,
    nearest_point,
    nearest_sq,
    within_fraction,
)

DIST_TOL = 1e-5   # metres: float32 differences of points within 1 m of the origin
TAU = 0.03


def _sets(rng, na=301, nb=517, spread=0.1, offset=0.7):
    a = rng.normal(0, spread, (na, 3)) + offset
    b = rng.normal(0, spread, (nb, 3)) + offset
    return a.astype(np.float32), b.astype(np.float32)


def reference_clipped(a, b, tau):
    """d_τ(A, B) by a double loop over NumPy rows: mean over a of min(τ, min_b ‖a − b‖)."""
    return float(np.mean([min(tau, np.min(np.linalg.norm(b - x, axis=1))) for x in a.astype(np.float64)]))


@pytest.mark.parametrize("chunk", [64, 100, 1024])
def test_nearest_matches_kdtree_with_masks_and_ragged_chunks(chunk):
    rng = np.random.default_rng(0)
    a, b = _sets(rng)
    mask = rng.random(len(b)) < 0.6
    ref_d, ref_i = cKDTree(b[mask].astype(np.float64)).query(a.astype(np.float64))
    d2 = np.asarray(nearest_sq(jnp.asarray(a), jnp.asarray(b), jnp.asarray(mask), chunk))
    np.testing.assert_allclose(np.sqrt(d2), ref_d, atol=DIST_TOL)
    d2p, point = nearest_point(jnp.asarray(a), jnp.asarray(b), jnp.asarray(mask), chunk)
    np.testing.assert_allclose(np.sqrt(np.asarray(d2p)), ref_d, atol=DIST_TOL)
    np.testing.assert_allclose(np.asarray(point), b[mask][ref_i], atol=DIST_TOL)


def test_no_valid_target_reports_far():
    a = jnp.zeros((5, 3))
    d2 = nearest_sq(a, jnp.ones((4, 3)), jnp.zeros(4, bool))
    assert np.all(np.asarray(d2) >= FAR)


def test_clipped_chamfer_matches_loop_reference():
    rng = np.random.default_rng(1)
    a, b = _sets(rng, 200, 150, spread=0.05)
    ma, mb = np.ones(len(a), bool), np.ones(len(b), bool)
    e, ab, ba = clipped_chamfer(jnp.asarray(a), jnp.asarray(ma), jnp.asarray(b), jnp.asarray(mb), TAU)
    ref_ab, ref_ba = reference_clipped(a, b, TAU), reference_clipped(b, a, TAU)
    np.testing.assert_allclose([float(ab), float(ba), float(e)], [ref_ab, ref_ba, ref_ab + ref_ba], atol=DIST_TOL)


def test_clipped_chamfer_properties():
    rng = np.random.default_rng(2)
    a, b = _sets(rng, 128, 96, spread=0.05)
    ones_a, ones_b = jnp.ones(len(a), bool), jnp.ones(len(b), bool)
    e_ab = float(clipped_chamfer(jnp.asarray(a), ones_a, jnp.asarray(b), ones_b, TAU)[0])
    e_ba = float(clipped_chamfer(jnp.asarray(b), ones_b, jnp.asarray(a), ones_a, TAU)[0])
    assert e_ab == pytest.approx(e_ba, abs=DIST_TOL)                                  # symmetric
    assert 0.0 <= e_ab <= 2 * TAU + DIST_TOL                                            # bounded by 2τ
    assert float(clipped_chamfer(jnp.asarray(a), ones_a, jnp.asarray(a), ones_a, TAU)[0]) == pytest.approx(0, abs=1e-6)
    shift = np.float32([0.3, -0.2, 0.1])
    e_shift = float(clipped_chamfer(jnp.asarray(a + shift), ones_a, jnp.asarray(b + shift), ones_b, TAU)[0])
    assert e_shift == pytest.approx(e_ab, abs=DIST_TOL)                                 # rigid invariance
    far = float(clipped_chamfer(jnp.asarray(a), ones_a, jnp.asarray(b + 10.0), ones_b, TAU)[0])
    assert far == pytest.approx(2 * TAU, abs=1e-6)                                      # clipped, not growing
    # padding with masked garbage changes nothing
    pad = np.concatenate([b, rng.normal(0, 5, (40, 3)).astype(np.float32)])
    mask = np.concatenate([np.ones(len(b), bool), np.zeros(40, bool)])
    e_pad = float(clipped_chamfer(jnp.asarray(a), ones_a, jnp.asarray(pad), jnp.asarray(mask), TAU)[0])
    assert e_pad == pytest.approx(e_ab, abs=DIST_TOL)


def test_within_fraction_counts_supported_queries():
    q = np.float32([[0, 0, 0], [0.02, 0, 0], [0.1, 0, 0], [5, 5, 5]])
    t = np.float32([[0, 0, 0]])
    frac = within_fraction(jnp.asarray(q), jnp.asarray([True, True, True, False]), jnp.asarray(t), jnp.ones(1, bool),
                           0.03)
    assert float(frac) == pytest.approx(2 / 3)
    assert float(clipped_distance(jnp.asarray(q[:3]), jnp.ones(3, bool), jnp.asarray(t), jnp.ones(1, bool), 0.03)) \
        == pytest.approx((0 + 0.02 + 0.03) / 3, abs=1e-7)


def test_hash_grid_is_exact_below_the_cell_size():
    rng = np.random.default_rng(3)
    a, b = _sets(rng, 400, 300, spread=0.05, offset=0.2)
    mask = rng.random(len(b)) < 0.8
    grid = build_grid(jnp.asarray(b), jnp.asarray(mask), TAU, table_size=1024, capacity=64)
    assert not bool(grid.overflow)
    d2 = np.asarray(nearest_grid(jnp.asarray(a), grid))
    ref, _ = cKDTree(b[mask].astype(np.float64)).query(a.astype(np.float64))
    near = ref < TAU
    np.testing.assert_allclose(np.sqrt(d2[near]), ref[near], atol=DIST_TOL)
    assert np.all(np.sqrt(d2[~near]) >= TAU - DIST_TOL)  # beyond the cell: "at least τ", all a clip needs
    clipped = np.minimum(np.sqrt(d2), TAU)
    np.testing.assert_allclose(clipped, np.minimum(ref, TAU), atol=DIST_TOL)


def test_hash_grid_reports_overflow():
    b = np.zeros((50, 3), np.float32) + np.float32([0.001, 0.002, 0.003])
    grid = build_grid(jnp.asarray(b), jnp.ones(50, bool), TAU, table_size=256, capacity=16)
    assert bool(grid.overflow)
