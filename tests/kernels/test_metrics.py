"""F1 at τ and the symmetric Chamfer distance against a NumPy reference, and known values."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from kernels.metrics import chamfer_cm, f1_score, geometry_metrics

TOL = 1e-5


def reference(pred, ref, tau):
    d_pr = np.array([np.min(np.linalg.norm(ref - p, axis=1)) for p in pred])
    d_rp = np.array([np.min(np.linalg.norm(pred - r, axis=1)) for r in ref])
    precision, recall = np.mean(d_pr <= tau), np.mean(d_rp <= tau)
    f1 = 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)
    return f1, precision, recall, 50.0 * (d_pr.mean() + d_rp.mean())


def _j(x):
    return jnp.asarray(x, jnp.float32), jnp.ones(len(x), bool)


def test_matches_reference_on_random_sets():
    rng = np.random.default_rng(0)
    pred = rng.normal(0, 0.05, (257, 3)) + 0.5
    ref = rng.normal(0, 0.05, (190, 3)) + 0.51
    for tau in (0.02, 0.04):
        f1, p, r = f1_score(*_j(pred), *_j(ref), tau)
        want = reference(pred, ref, tau)
        np.testing.assert_allclose([float(f1), float(p), float(r)], want[:3], atol=TOL)
    assert float(chamfer_cm(*_j(pred), *_j(ref))) == pytest.approx(want[3], abs=1e-3)
    f1s, _, _, cd = geometry_metrics(*_j(pred), *_j(ref), taus=(0.02, 0.04))
    assert float(cd) == pytest.approx(want[3], abs=1e-3)
    assert float(f1s[1]) == pytest.approx(want[0], abs=TOL)


def test_known_values_for_parallel_planes():
    g = np.stack(np.meshgrid(np.linspace(0, 0.2, 21), np.linspace(0, 0.2, 21), indexing="ij"), -1).reshape(-1, 2)
    a = np.column_stack([g, np.zeros(len(g))])
    b = a + [0, 0, 0.03]  # 3 cm apart
    f1, _, _, cd = geometry_metrics(*_j(a), *_j(b), taus=(0.02, 0.04))
    assert float(cd) == pytest.approx(3.0, abs=1e-4)
    np.testing.assert_allclose(np.asarray(f1), [0.0, 1.0], atol=TOL)


def test_identity_symmetry_and_masks():
    rng = np.random.default_rng(1)
    a = rng.normal(0, 0.05, (100, 3))
    b = rng.normal(0, 0.05, (80, 3))
    f1, p, r = f1_score(*_j(a), *_j(a), 0.001)
    assert float(f1) == pytest.approx(1.0) and float(chamfer_cm(*_j(a), *_j(a))) == pytest.approx(0.0, abs=1e-5)
    assert float(chamfer_cm(*_j(a), *_j(b))) == pytest.approx(float(chamfer_cm(*_j(b), *_j(a))), abs=1e-5)
    # F1 grows with τ
    values = [float(f1_score(*_j(a), *_j(b), t)[0]) for t in (0.005, 0.01, 0.02, 0.04)]
    assert values == sorted(values)
    # masked rows are ignored
    padded = np.concatenate([b, np.full((30, 3), 9.0)])
    mask = jnp.asarray(np.arange(len(padded)) < len(b))
    assert float(chamfer_cm(*_j(a), jnp.asarray(padded, jnp.float32), mask)) == pytest.approx(
        float(chamfer_cm(*_j(a), *_j(b))), abs=1e-5)
