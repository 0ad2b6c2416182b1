"""The one internal camera record.

Convention (docs/architecture.md "Contracts"): OpenCV axes (x right, y down, z forward),
``world_to_camera`` 4×4, pinhole ``K``, pixel centres at (i + 0.5, j + 0.5) in K's
image coordinates (the COLMAP / gsplat convention). Lens distortion, when the
source model has it, is kept in ``distortion`` (OpenCV order k1, k2, p1, p2[, k3, ...])
and reported; the renderer itself is pinhole.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from contextvars import ContextVar
from pathlib import Path

import numpy as np

from phirie_jax.errors import SceneInputError
from phirie_jax.types import Camera

# Pose matrices in text files are often printed with ~7 digits; farther from a
# rotation than this is a scaled or sheared matrix, not a camera pose.
RIGID_TOLERANCE = 1e-3
# Below this the rotation is already orthonormal to float precision and kept bit for bit.
_ORTHONORMAL_EXACT = 1e-12


_outside_allowed: ContextVar[bool] = ContextVar("phirie_outside_paths_allowed", default=False)


@contextlib.contextmanager
def outside_paths_allowed(allowed: bool = True) -> Iterator[None]:
    """Inside, camera files may name images outside their folder (``--allow-outside-paths``);
    by default such an image is refused before anything opens it."""
    token = _outside_allowed.set(allowed)
    try:
        yield
    finally:
        _outside_allowed.reset(token)


def check_inside(image_path: Path, folder: Path, source: Path, field: str, written: str,
                 scene_root: Path | None = None) -> None:
    """Refuse an image a camera file (``source``) names outside ``folder``, the folder its paths are
    relative to, or that is a symbolic link (itself or a folder on its way) to a file outside
    ``scene_root`` (default ``folder``): a ``transforms.json`` frame or a COLMAP image name of
    ``../../etc/hostname`` or ``/etc/hostname``, or ``images/x.jpg`` linking to ``/etc/passwd``, would
    otherwise be opened and read. ``written`` is the path as the file has it. The test is on the
    path as written (``..`` resolved), then on where its links lead. ``outside_paths_allowed`` lifts it.
    """
    if _outside_allowed.get():
        return
    folder, image = os.path.abspath(folder), os.path.abspath(image_path)
    if os.path.commonpath([folder, image]) != folder:
        raise SceneInputError(source, field, f"{written!r} is outside {folder} (expected an image inside the "
                              "scene folder; --allow-outside-paths reads it anyway)")
    refuse_link_outside(Path(image), Path(scene_root or folder), source, field, written)


def refuse_link_outside(path: Path, scene_root: Path, source: Path | str, field: str, written: str) -> None:
    """Refuse ``path`` when following its symbolic links leads outside ``scene_root`` (unless
    ``outside_paths_allowed``)."""
    if _outside_allowed.get():
        return
    root, real = os.path.realpath(scene_root), os.path.realpath(path)
    if os.path.commonpath([root, real]) != root:
        raise SceneInputError(source, field, f"{written!r} is a symbolic link to {real}, outside {root} (expected "
                              "a file inside the scene folder; --allow-outside-paths reads it anyway)")


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """(3, 3) pinhole matrix."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)


def sort_by_name(cameras: list[Camera]) -> list[Camera]:
    """Camera index k = k-th image in name order (docs/architecture.md "Contracts")."""
    return sorted(cameras, key=lambda c: c.name)


def rigid(matrix: np.ndarray, path: str | Path, field: str, tolerance: float = RIGID_TOLERANCE) -> np.ndarray:
    """(4, 4) rigid transform from a (4, 4) or (3, 4) matrix that is one up to ``tolerance``.

    The rotation is replaced by its nearest rotation (SVD) unless it is orthonormal to
    float precision already. Raises ``SceneInputError`` naming ``path`` and ``field``.
    """
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4):
        raise SceneInputError(path, field, f"expected a 4x4 (or 3x4) matrix, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        row, col = (int(i) for i in np.argwhere(~np.isfinite(m))[0])
        raise SceneInputError(path, field, f"non-finite value {m[row, col]} at row {row}, column {col} "
                              f"({int((~np.isfinite(m)).sum())} in all; expected finite numbers)")
    if np.abs(m[3] - (0.0, 0.0, 0.0, 1.0)).max() > tolerance:
        raise SceneInputError(path, field, f"last row {m[3].tolist()} (expected 0 0 0 1)")
    rot = m[:3, :3]
    deviation = np.abs(rot.T @ rot - np.eye(3)).max()
    if deviation > tolerance or np.linalg.det(rot) <= 0:
        raise SceneInputError(
            path, field, f"rotation part is not a rotation (|RᵀR − I| = {deviation:.2g}, det = "
            f"{np.linalg.det(rot):.4g}; expected a rigid pose without scale or reflection)",
        )
    out = np.eye(4)
    out[:3, 3] = m[:3, 3]
    if deviation <= _ORTHONORMAL_EXACT:
        out[:3, :3] = rot
    else:
        u, _, vt = np.linalg.svd(rot)
        out[:3, :3] = u @ vt
    return out
