"""Host geometry helpers by their properties."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from phirie_jax.geometry import edge_keys, logit, rotation_to_z, sigmoid, sim3_matrix, split_sim3

ROTATION_TOLERANCE = 1e-10


@pytest.mark.parametrize("up", [(0, 0, 1), (0, 0, -1), (1, 0, 0), (0, -1, 0), (0.3, -0.2, 0.9), (1e-3, 0, -1)])
def test_rotation_to_z_is_a_proper_rotation_taking_up_to_z(up):
    rot = rotation_to_z(np.asarray(up, float) * 2.5)
    assert np.allclose(rot @ rot.T, np.eye(3), atol=ROTATION_TOLERANCE)
    assert np.linalg.det(rot) == pytest.approx(1.0)
    unit = np.asarray(up, float) / np.linalg.norm(up)
    assert np.allclose(rot @ unit, [0, 0, 1], atol=ROTATION_TOLERANCE)


def test_rotation_to_z_is_the_smallest_rotation():
    rng = np.random.default_rng(0)
    for up in rng.normal(size=(20, 3)):
        up /= np.linalg.norm(up)
        angle = np.degrees(Rotation.from_matrix(rotation_to_z(up)).magnitude())
        assert angle == pytest.approx(np.degrees(np.arccos(up[2])), abs=1e-6)


def test_sim3_split_inverts_compose_and_refuses_non_similarities():
    rot = Rotation.from_rotvec([0.3, -0.5, 1.1]).as_matrix()
    scale, r, t = split_sim3(sim3_matrix(0.37, rot, [1.0, 2.0, -3.0]))
    assert scale == pytest.approx(0.37)
    assert np.allclose(r, rot) and np.allclose(t, [1.0, 2.0, -3.0])
    for bad in (np.diag([1.0, 2.0, 1.0, 1.0]), np.diag([1.0, 1.0, -1.0, 1.0]), np.full((4, 4), np.nan), np.eye(3)):
        with pytest.raises(ValueError):
            split_sim3(bad)


def test_sigmoid_and_logit_are_inverse_and_do_not_overflow():
    p = np.linspace(0.01, 0.99, 33)
    assert np.allclose(sigmoid(logit(p)), p)
    with np.errstate(over="raise", invalid="raise", divide="raise"):
        assert np.allclose(sigmoid(np.array([-1e4, 0.0, 1e4])), [0.0, 0.5, 1.0])


def test_edge_keys_order_and_group_pairs_as_rows_do():
    pairs = np.random.default_rng(3).integers(0, 50, (400, 2))
    rows, row_inverse, row_counts = np.unique(pairs, axis=0, return_inverse=True, return_counts=True)
    keys, key_inverse, key_counts = np.unique(edge_keys(pairs, 50), return_inverse=True, return_counts=True)
    assert len(keys) == len(rows)
    np.testing.assert_array_equal(key_inverse.reshape(-1), row_inverse.reshape(-1))
    np.testing.assert_array_equal(key_counts, row_counts)
