"""Host rotations (phirie_jax.rotations): against MuJoCo's mju_* and SciPy as references, and by
their properties (round trip, unit norm, sign ambiguity, composition, batching)."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from phirie_jax import rotations as rot

TOL = 1e-12        # float64 conversions of the same rotation by two implementations


@pytest.fixture
def quats() -> np.ndarray:
    """(64, 4) unit wxyz: random ones, the identity, half turns and a near-half turn."""
    rng = np.random.default_rng(0)
    q = rng.normal(size=(58, 4))
    special = np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1],
                        [1e-9, 0, 0, 1], [0.5, 0.5, 0.5, 0.5]], float)
    q = np.concatenate([q, special])
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _mju_matrix(q: np.ndarray) -> np.ndarray:
    out = np.zeros(9)
    mujoco.mju_quat2Mat(out, q)
    return out.reshape(3, 3)


def test_quat_to_matrix_matches_mujoco(quats):
    mats = rot.quat_to_matrix(quats)
    assert mats.shape == (len(quats), 3, 3)
    for q, m in zip(quats, mats):
        np.testing.assert_allclose(m, _mju_matrix(q), atol=TOL)


def test_matrix_to_quat_matches_mujoco_up_to_sign(quats):
    mats = rot.quat_to_matrix(quats)
    got = rot.matrix_to_quat(mats)
    for m, q in zip(mats, got):
        ref = np.zeros(4)
        mujoco.mju_mat2Quat(ref, m.ravel())
        sign = 1.0 if q @ ref >= 0 else -1.0
        np.testing.assert_allclose(q, sign * ref, atol=1e-9)


def test_wxyz_is_scalar_first():
    """A quarter turn about +z is (cos 45°, 0, 0, sin 45°) and takes +x to +y."""
    q = rot.yaw_quat(np.pi / 2)
    np.testing.assert_allclose(q, [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], atol=TOL)
    np.testing.assert_allclose(rot.quat_to_matrix(q) @ [1.0, 0, 0], [0, 1.0, 0], atol=TOL)
    np.testing.assert_allclose(rot.yaw_matrix(np.pi / 2), rot.quat_to_matrix(q), atol=TOL)


def test_round_trip_unit_norm_and_sign(quats):
    back = rot.matrix_to_quat(rot.quat_to_matrix(quats))
    np.testing.assert_allclose(np.linalg.norm(back, axis=1), 1.0, atol=TOL)
    # q and −q are one rotation: the round trip returns one of them
    assert np.all(np.abs(np.abs(np.sum(back * quats, axis=1)) - 1.0) < 1e-9)
    np.testing.assert_allclose(rot.quat_to_matrix(-quats), rot.quat_to_matrix(quats), atol=TOL)
    # an unnormalized quaternion is the same rotation as its unit one
    np.testing.assert_allclose(rot.quat_to_matrix(3.5 * quats), rot.quat_to_matrix(quats), atol=TOL)


def test_matrices_are_rotations(quats):
    mats = rot.quat_to_matrix(quats)
    np.testing.assert_allclose(mats @ np.swapaxes(mats, -1, -2), np.broadcast_to(np.eye(3), mats.shape), atol=TOL)
    np.testing.assert_allclose(np.linalg.det(mats), 1.0, atol=TOL)


def test_multiply_composes_matrices(quats):
    a, b = quats[:32], quats[32:]
    ab = rot.quat_multiply(a, b)
    np.testing.assert_allclose(rot.quat_to_matrix(ab), rot.quat_to_matrix(a) @ rot.quat_to_matrix(b), atol=1e-12)
    for x, y, z in zip(a, b, ab):   # MuJoCo's product, same convention
        ref = np.zeros(4)
        mujoco.mju_mulQuat(ref, x, y)
        np.testing.assert_allclose(z, ref, atol=TOL)
    identity = np.array([1.0, 0, 0, 0])
    np.testing.assert_array_equal(rot.quat_multiply(identity, quats), quats)
    # no normalization: norms multiply
    np.testing.assert_allclose(np.linalg.norm(rot.quat_multiply(2 * a, 3 * b), axis=1), 6.0, atol=1e-12)


def test_compose_is_the_product_of_rotations(quats):
    a, b = quats[:32], quats[32:]
    ab = rot.compose(a, b)
    np.testing.assert_allclose(ab, rot.quat_multiply(a, b), atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(ab, axis=1), 1.0, atol=TOL)
    np.testing.assert_allclose(rot.quat_to_matrix(ab), rot.quat_to_matrix(a) @ rot.quat_to_matrix(b), atol=TOL)
    assert rot.compose(a[0], b).shape == (32, 4)
    # composing with a yaw turns about the composed frame's z: the matrix product, exactly as SciPy
    turn = rot.yaw_quat(0.7)
    np.testing.assert_array_equal(rot.compose(a[0], turn),
                                  (Rotation.from_quat(a[0], scalar_first=True) * Rotation.from_euler("z", 0.7))
                                  .as_quat(scalar_first=True))


def test_rotvec_round_trip_and_angle(quats):
    rng = np.random.default_rng(1)
    vecs = rng.normal(size=(20, 3))
    vecs *= (rng.uniform(0.0, np.pi - 1e-3, 20) / np.linalg.norm(vecs, axis=1))[:, None]
    mats = rot.rotvec_to_matrix(vecs)
    np.testing.assert_allclose(rot.matrix_to_rotvec(mats), vecs, atol=1e-9)
    ref = np.stack([_mju_matrix(Rotation.from_rotvec(v).as_quat(scalar_first=True)) for v in vecs])
    np.testing.assert_allclose(mats, ref, atol=TOL)
    # the angle between two quaternions is the rotation vector's length, sign-blind
    a, b = quats[:20], rot.matrix_to_quat(mats @ rot.quat_to_matrix(quats[:20]))
    np.testing.assert_allclose(rot.quat_angle(a, b), np.linalg.norm(vecs, axis=1), atol=1e-9)
    np.testing.assert_allclose(rot.quat_angle(a, -b), np.linalg.norm(vecs, axis=1), atol=1e-9)
    assert rot.quat_angle(a[0], a[0]).shape == ()
    assert float(rot.quat_angle(a[0], a[0])) < 1e-7


def test_pose_matrix(quats):
    rng = np.random.default_rng(2)
    pos = rng.normal(size=(5, 7, 3))
    q = quats[:35].reshape(5, 7, 4)
    pose = rot.pose_matrix(pos, q)
    assert pose.shape == (5, 7, 4, 4)
    np.testing.assert_allclose(pose[..., :3, :3], rot.quat_to_matrix(q), atol=0)
    np.testing.assert_array_equal(pose[..., :3, 3], pos)
    np.testing.assert_array_equal(pose[..., 3, :], np.broadcast_to([0, 0, 0, 1.0], (5, 7, 4)))


def test_slerp_ends_and_middle():
    start, end = np.eye(3), rot.yaw_matrix(1.2)
    np.testing.assert_allclose(rot.slerp_matrix(start, end, 0.0), start, atol=TOL)
    np.testing.assert_allclose(rot.slerp_matrix(start, end, 1.0), end, atol=TOL)
    np.testing.assert_allclose(rot.slerp_matrix(start, end, 0.25), rot.yaw_matrix(0.3), atol=TOL)
    assert rot.slerp_matrix(start, end, np.linspace(0, 1, 5)).shape == (5, 3, 3)


def test_batch_axes_are_kept_and_rows_match_single_calls(quats):
    q = quats[:24].reshape(2, 3, 4, 4)
    mats = rot.quat_to_matrix(q)
    assert mats.shape == (2, 3, 4, 3, 3)
    np.testing.assert_array_equal(mats[1, 2, 3], rot.quat_to_matrix(q[1, 2, 3]))
    back = rot.matrix_to_quat(mats)
    assert back.shape == (2, 3, 4, 4)
    np.testing.assert_array_equal(back[0, 1, 2], rot.matrix_to_quat(mats[0, 1, 2]))


@pytest.mark.parametrize("fn, bad", [(rot.quat_to_matrix, np.zeros(3)), (rot.matrix_to_quat, np.eye(4)),
                                     (rot.matrix_to_rotvec, np.zeros((3, 2)))])
def test_wrong_shapes_are_refused(fn, bad):
    with pytest.raises(ValueError, match="expected shape"):
        fn(bad)


def test_kernel_versions_agree(quats):
    """The jitted kernels (kernels/gaussians.py) are the same conversions in float32."""
    import jax.numpy as jnp

    from kernels.gaussians import quat_to_rotmat, rotmat_to_quat

    np.testing.assert_allclose(np.asarray(quat_to_rotmat(jnp.asarray(quats, jnp.float32))),
                               rot.quat_to_matrix(quats), atol=1e-5)
    kq = np.asarray(rotmat_to_quat(jnp.asarray(rot.quat_to_matrix(quats), jnp.float32)))
    assert np.all(np.abs(np.abs(np.sum(kq * quats, axis=1)) - 1.0) < 1e-5)
