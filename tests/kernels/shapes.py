"""Point-sampled test shapes (NumPy only) and partial views of them."""

from __future__ import annotations

import numpy as np

from kernels.registration import UP_AXES, axis_rotation

# An L-shaped block: a long low box with a tall box on one end (no rotational symmetry).
L_BOXES = (((0.0, 0.0, 0.0), (0.12, 0.06, 0.04)), ((0.0, 0.0, 0.04), (0.04, 0.06, 0.10)))
VIEWS = np.array([[-1.0, -1.0, 1.0], [1.0, -1.0, 1.0], [0.0, -1.0, 0.6], [0.0, 0.0, 1.0]])


def box_surface(lo, size, n, rng):
    """(n, 3) points and normals uniformly on the surface of an axis-aligned box."""
    lo, size = np.asarray(lo, float), np.asarray(size, float)
    areas = np.array([size[1] * size[2], size[0] * size[2], size[0] * size[1]] * 2)
    face = rng.choice(6, size=n, p=areas / areas.sum())
    u = rng.random((n, 3))
    pts = lo + u * size
    axis = face % 3
    side = face // 3  # 0: low face, 1: high face
    pts[np.arange(n), axis] = lo[axis] + side * size[axis]
    normals = np.zeros((n, 3))
    normals[np.arange(n), axis] = np.where(side == 1, 1.0, -1.0)
    return pts, normals


def l_shape(n, rng, boxes=L_BOXES):
    parts = [box_surface(lo, size, n // len(boxes), rng) for lo, size in boxes]
    pts = np.concatenate([p for p, _ in parts])
    normals = np.concatenate([q for _, q in parts])
    pts[:, :2] -= pts[:, :2].mean(0)  # centred on the z axis, resting on z = 0
    return pts, normals


def partial_view(points, normals, count, rng, views=VIEWS):
    """Points whose normal faces one of ``views`` (no occlusion), none on the bottom."""
    seen = np.any(normals @ views.T > 0.1, axis=1) & (points[:, 2] > 1e-4)
    keep = np.flatnonzero(seen)
    return points[rng.choice(keep, size=min(count, len(keep)), replace=False)]


def yaw_rotation(yaw):
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def in_random_frame(points, axis_index, rng):
    """The shape as an external generator would give it: up = UP_AXES[axis_index], random yaw,
    unit-box scale, centred. → (points in that frame, 4×4 truth: frame → world)."""
    to_file = axis_rotation(UP_AXES[axis_index]).T @ yaw_rotation(rng.uniform(0, 2 * np.pi))
    p = points @ to_file.T
    centre = p.mean(0)
    size = float(np.max(p.max(0) - p.min(0)))
    truth = np.eye(4)
    truth[:3, :3] = size * to_file.T
    truth[:3, 3] = to_file.T @ centre
    return ((p - centre) / size).astype(np.float32), truth


def padded(q, bucket):
    out = np.zeros((bucket, 3), np.float32)
    out[: len(q)] = q
    mask = np.zeros(bucket, bool)
    mask[: len(q)] = True
    return out, mask
