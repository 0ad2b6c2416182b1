"""RGB-D sequences in the Open3D / Redwood layout.

A trajectory ``.log`` holds, per frame, a header line of three integers and four lines
of a 4×4 camera-to-world matrix (camera axes as OpenCV's: x right, y down, z forward,
which is how Open3D back-projects depth). The intrinsics json is Open3D's
``PinholeCameraIntrinsic``: ``width``, ``height`` and a column-major ``intrinsic_matrix``
whose principal point counts pixel centres at integers; ``Camera`` counts them at +0.5,
so 0.5 is added to cx and cy.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from phirie_jax.errors import SceneInputError
from phirie_jax.io.camera import Camera, rigid

# Logs print poses with as few as 6 digits; this admits that rounding, not a scale.
LOG_RIGID_TOLERANCE = 1e-4
_COLOR_EXTENSIONS = (".jpg", ".jpeg", ".png")


@dataclasses.dataclass(frozen=True)
class Intrinsics:
    K: np.ndarray  # (3, 3) float64, pixel centres at +0.5
    width: int
    height: int


def read_trajectory_log(path: str | Path) -> list[np.ndarray]:
    """Camera-to-world (4, 4) float64 matrices, one per frame, in file order.

    Each is checked to be rigid up to ``LOG_RIGID_TOLERANCE`` and returned as written.
    """
    path = Path(path)
    try:
        lines = [(n, line.split()) for n, line in enumerate(path.read_text().splitlines(), start=1)]
    except FileNotFoundError:
        raise SceneInputError(path, None, "file not found") from None
    except UnicodeDecodeError:
        raise SceneInputError(path, None, "not a text file (expected a Redwood .log trajectory)") from None
    lines = [(n, tokens) for n, tokens in lines if tokens]
    if len(lines) % 5:
        raise SceneInputError(
            path, None, f"{len(lines)} non-empty lines (expected 5 per frame: a header of 3 integers, then 4 rows)"
        )
    poses = []
    for start in range(0, len(lines), 5):
        number, header = lines[start]
        frame = f"frame {start // 5} (line {number})"
        if len(header) != 3 or not all(_is_int(t) for t in header):
            raise SceneInputError(path, frame, f"header {' '.join(header)!r} (expected 3 integers)")
        rows = []
        for number, tokens in lines[start + 1: start + 5]:
            try:
                row = [float(t) for t in tokens]
            except ValueError:
                row = []
            if len(row) != 4:
                raise SceneInputError(path, f"line {number}", f"{' '.join(tokens)!r} (expected 4 numbers)")
            rows.append(row)
        matrix = np.asarray(rows, dtype=np.float64)
        rigid(matrix, path, frame, LOG_RIGID_TOLERANCE)  # raises when not a pose
        poses.append(matrix)
    return poses


def read_primesense_intrinsics(path: str | Path) -> Intrinsics:
    """Open3D ``PinholeCameraIntrinsic`` json → K (pixel centres at +0.5), width, height."""
    path = Path(path)
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SceneInputError(path, None, "file not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise SceneInputError(path, None, f"not valid JSON ({e})") from None
    if not isinstance(meta, dict):
        raise SceneInputError(path, None, "expected an object with width, height and intrinsic_matrix")
    size = []
    for key in ("width", "height"):
        value = meta.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            raise SceneInputError(path, key, f"{value!r} (expected a positive integer)")
        size.append(value)
    values = meta.get("intrinsic_matrix")
    numbers = isinstance(values, list) and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in values
    )
    if not numbers or len(values) != 9:
        raise SceneInputError(path, "intrinsic_matrix", "expected 9 numbers (a column-major 3x3 matrix)")
    K = np.asarray(values, dtype=np.float64).reshape(3, 3).T  # stored column by column
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[0, 1] != 0 or K[1, 0] != 0 or np.any(K[2] != (0.0, 0.0, 1.0)):
        raise SceneInputError(path, "intrinsic_matrix", f"{K.tolist()} (expected a pinhole matrix, focal > 0)")
    K[:2, 2] += 0.5
    return Intrinsics(K=K, width=size[0], height=size[1])


def read_rgbd_cameras(intrinsics_path: str | Path, trajectory_path: str | Path,
                      color_dir: str | Path) -> list[Camera]:
    """One ``Camera`` per colour image of ``color_dir`` (name order) with the log's poses.

    ``world_to_camera`` is the inverse of the frame's camera-to-world (rotation projected
    onto the nearest rotation first); names are the colour file names.
    """
    intrinsics = read_primesense_intrinsics(intrinsics_path)
    poses = read_trajectory_log(trajectory_path)
    color_dir = Path(color_dir).absolute()
    if not color_dir.is_dir():
        raise SceneInputError(color_dir, None, "colour image folder not found")
    images = sorted((p for p in color_dir.iterdir() if p.suffix.lower() in _COLOR_EXTENSIONS and p.is_file()),
                    key=lambda p: p.name)
    if len(images) != len(poses):
        raise SceneInputError(
            trajectory_path, None,
            f"{len(poses)} poses for {len(images)} colour images in {color_dir} (expected one each)",
        )
    cameras = []
    for image, pose in zip(images, poses):
        c2w = rigid(pose, trajectory_path, image.name, LOG_RIGID_TOLERANCE)
        w2c = np.eye(4)
        w2c[:3, :3] = c2w[:3, :3].T
        w2c[:3, 3] = -c2w[:3, :3].T @ c2w[:3, 3]
        cameras.append(Camera(name=image.name, K=intrinsics.K.copy(), world_to_camera=w2c,
                              width=intrinsics.width, height=intrinsics.height, image_path=image))
    return cameras


def _is_int(token: str) -> bool:
    try:
        int(token)
    except ValueError:
        return False
    return True
