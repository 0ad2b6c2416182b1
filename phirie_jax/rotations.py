"""Host rotations (NumPy, float64): the one home for quaternion, matrix and rotation-vector conversions.

Convention: a quaternion is (w, x, y, z), scalar first, as MuJoCo stores it (``qpos``, ``xquat``,
``geom_quat``, MJCF ``quat``) and as a Gaussian PLY stores ``rot_0..3``. A rotation matrix acts on
column vectors (v' = R v), so ``quat_to_matrix(q) @ v`` rotates v by q. q and −q are the same rotation;
functions that return a quaternion do not choose a sign unless they say so. Every function takes
leading batch axes: quaternions (..., 4), matrices (..., 3, 3), rotation vectors (..., 3).

SciPy's ``Rotation`` does the arithmetic (one implementation for every caller: the files the
pipeline writes depend on its exact rounding); ``tests/test_rotations.py`` checks it against
MuJoCo's ``mju_*`` and by the rotations' properties. Jitted code uses the traced versions in
``kernels/gaussians.py`` (``quat_to_rotmat``, ``rotmat_to_quat``, ``quat_multiply``).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


def _batched(values, tail: tuple[int, ...], name: str) -> np.ndarray:
    values = np.asarray(values, np.float64)
    if values.shape[values.ndim - len(tail):] != tail:
        raise ValueError(f"{name}: expected shape (..., {', '.join(map(str, tail))}), got {values.shape}")
    return values


def _apply(fn, values: np.ndarray, tail: int, out_tail: tuple[int, ...]) -> np.ndarray:
    """``fn`` over the rows of ``values`` flattened to (N, *tail), reshaped back to (..., *out_tail)."""
    lead = values.shape[:values.ndim - tail]
    flat = values.reshape((-1,) + values.shape[values.ndim - tail:])
    return np.asarray(fn(flat)).reshape(lead + out_tail)


def quat_to_matrix(quat) -> np.ndarray:
    """(..., 4) wxyz (normalized here; a zero quaternion is a ``ValueError``) → (..., 3, 3)."""
    quat = _batched(quat, (4,), "quaternion")
    return _apply(lambda q: Rotation.from_quat(q, scalar_first=True).as_matrix(), quat, 1, (3, 3))


def matrix_to_quat(matrix) -> np.ndarray:
    """(..., 3, 3) rotation (the nearest one, if not exactly orthonormal) → (..., 4) unit wxyz."""
    matrix = _batched(matrix, (3, 3), "rotation matrix")
    return _apply(lambda m: Rotation.from_matrix(m).as_quat(scalar_first=True), matrix, 2, (4,))


def quat_multiply(a, b) -> np.ndarray:
    """Hamilton product a ⊗ b of any (..., 4) wxyz quaternions (broadcast), bilinear and not
    normalized: it turns a Gaussian's stored quaternion, whatever its norm, by a rotation a. For
    rotations, ``compose``."""
    w0, x0, y0, z0 = np.moveaxis(_batched(a, (4,), "quaternion a"), -1, 0)
    w, x, y, z = np.moveaxis(_batched(b, (4,), "quaternion b"), -1, 0)
    return np.stack([w0 * w - x0 * x - y0 * y - z0 * z, w0 * x + x0 * w + y0 * z - z0 * y,
                     w0 * y - x0 * z + y0 * w + z0 * x, w0 * z + x0 * y - y0 * x + z0 * w], axis=-1)


def compose(a, b) -> np.ndarray:
    """(..., 4) unit wxyz of the rotation b, then a, of unit (..., 4) wxyz quaternions (broadcast)."""
    a, b = np.broadcast_arrays(_batched(a, (4,), "quaternion a"), _batched(b, (4,), "quaternion b"))
    lead = a.shape[:-1]
    product = (Rotation(a.reshape(-1, 4), normalize=False, scalar_first=True)
               * Rotation(b.reshape(-1, 4), normalize=False, scalar_first=True))
    return product.as_quat(scalar_first=True).reshape(lead + (4,))


def yaw_quat(angle) -> np.ndarray:
    """(..., 4) wxyz of the rotation by ``angle`` (...,) radians about +z."""
    angle = np.asarray(angle, np.float64)
    return _apply(lambda a: Rotation.from_euler("z", a[:, None]).as_quat(scalar_first=True),
                  angle[..., None], 1, (4,))


def yaw_matrix(angle) -> np.ndarray:
    """(..., 3, 3) rotation by ``angle`` (...,) radians about +z."""
    angle = np.asarray(angle, np.float64)
    return _apply(lambda a: Rotation.from_euler("z", a[:, None]).as_matrix(), angle[..., None], 1, (3, 3))


def rotvec_to_matrix(rotvec) -> np.ndarray:
    """(..., 3) axis × angle (radians) → (..., 3, 3)."""
    rotvec = _batched(rotvec, (3,), "rotation vector")
    return _apply(lambda v: Rotation.from_rotvec(v).as_matrix(), rotvec, 1, (3, 3))


def matrix_to_rotvec(matrix) -> np.ndarray:
    """(..., 3, 3) rotation → (..., 3) axis × angle, the angle in [0, π]."""
    matrix = _batched(matrix, (3, 3), "rotation matrix")
    return _apply(lambda m: Rotation.from_matrix(m).as_rotvec(), matrix, 2, (3,))


def quat_angle(q0, q1) -> np.ndarray:
    """(...,) angle in radians, in [0, π], of the rotation taking q0 to q1 ((..., 4) wxyz, broadcast;
    each normalized here), whatever either one's sign."""
    q0 = _batched(q0, (4,), "quaternion q0")
    q1 = _batched(q1, (4,), "quaternion q1")
    q0, q1 = np.broadcast_arrays(q0, q1)
    lead = q0.shape[:-1]
    r0 = Rotation.from_quat(q0.reshape(-1, 4), scalar_first=True)
    r1 = Rotation.from_quat(q1.reshape(-1, 4), scalar_first=True)
    return np.asarray((r1 * r0.inv()).magnitude()).reshape(lead)


def pose_matrix(position, quat) -> np.ndarray:
    """(..., 4, 4) rigid transforms from positions (..., 3) and wxyz quaternions (..., 4), e.g. MuJoCo's
    ``xpos`` and ``xquat``."""
    position = _batched(position, (3,), "position")
    rot = quat_to_matrix(quat)
    out = np.zeros(rot.shape[:-2] + (4, 4))
    out[..., :3, :3], out[..., :3, 3], out[..., 3, 3] = rot, position, 1.0
    return out


def slerp_matrix(start, end, s) -> np.ndarray:
    """(3, 3) the rotation a fraction ``s`` in [0, 1] of the shortest way from ``start`` (3, 3) to
    ``end`` (3, 3); an array ``s`` (K,) gives (K, 3, 3)."""
    turn = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([_batched(start, (3, 3), "start"),
                                                            _batched(end, (3, 3), "end")])))
    return turn(s).as_matrix()
