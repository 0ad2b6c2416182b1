"""Host geometry helpers (NumPy): the rotation taking a direction to +z, Sim(3) split, sigmoid,
mesh edges as integer keys.

Kernels carry their own traced versions; this is the host's one home for each.
"""

from __future__ import annotations

import numpy as np

Z = np.array([0.0, 0.0, 1.0])


def rotation_to_z(up: np.ndarray) -> np.ndarray:
    """(3, 3) the smallest proper rotation taking ``up`` (3,) (any length > 0) to +z.

    For −z, where every half turn is smallest, the half turn about x."""
    up = np.asarray(up, np.float64)
    up = up / np.linalg.norm(up)
    c = float(up @ Z)
    if c > 1 - 1e-12:
        return np.eye(3)
    if c < -1 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    k = np.cross(up, Z)
    s = np.linalg.norm(k)
    k /= s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * K + (1 - c) * K @ K  # Rodrigues


def split_sim3(pose: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """A (4, 4) Sim(3) → (scale, (3, 3) rotation, (3,) translation); ``ValueError`` otherwise."""
    pose = np.asarray(pose, np.float64)
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise ValueError("pose: expected a finite 4×4 matrix")
    block = pose[:3, :3]
    det = float(np.linalg.det(block))
    if det <= 0:
        raise ValueError(f"pose: rotation block has determinant {det:.3g} (expected a positive similarity)")
    scale = det ** (1.0 / 3.0)
    rot = block / scale
    if not np.allclose(rot.T @ rot, np.eye(3), atol=1e-4):
        raise ValueError("pose: rotation block is not a uniform scale times a rotation")
    u, _, vt = np.linalg.svd(rot)
    return scale, u @ vt, pose[:3, 3].copy()


def sim3_matrix(scale: float, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(4, 4) Sim(3) from scale, (3, 3) rotation and (3,) translation."""
    out = np.eye(4)
    out[:3, :3] = scale * np.asarray(rotation, np.float64)
    out[:3, 3] = translation
    return out


def sigmoid(x: np.ndarray) -> np.ndarray:
    """Logistic function (opacity from a stored logit), without overflow warnings."""
    with np.errstate(over="ignore", under="ignore"):
        return 1.0 / (1.0 + np.exp(-np.asarray(x, np.float64)))


def logit(p: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Inverse of ``sigmoid`` with ``p`` clipped to [eps, 1 − eps]."""
    p = np.clip(np.asarray(p, np.float64), eps, 1 - eps)
    return np.log(p / (1 - p))


def edge_keys(edges: np.ndarray, count: int) -> np.ndarray:
    """(E,) int64 key of each (E, 2) vertex pair of a mesh of ``count`` vertices: equal pairs,
    equal keys, in the pairs' lexicographic order (a 1-D ``np.unique`` instead of one over rows,
    many times faster); a key k is the pair (k // count, k % count)."""
    return np.asarray(edges[:, 0], np.int64) * max(int(count), 1) + edges[:, 1]
