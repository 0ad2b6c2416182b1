"""Instance masks from 3D box prompts: one labelled image per view, no segmenter needed.

A box prompt is an axis-aligned box in the capture frame with an instance id (or, given a
``rotation``, a box axis-aligned in a rotated frame: an oriented box, for an object against
a wall that is not along the capture's axes). At each
camera the source Gaussians are rendered; every pixel whose accumulated alpha is at least
``min_alpha`` is back-projected at its alpha-normalized depth (``depth / alpha``, the
expected depth of what the pixel sees), and takes the id of the first box (in the order
given) that holds its 3D point. Each id's pixels are then cleaned with a morphological
open (specks from floaters and needles) and close (pinholes), and the views are written
like ``masks/``: ``<image stem>.png``, 16-bit, 0 = none, k = instance k
(``phirie_jax.io.scene``, ``phirie_jax.observe.masks.file_masks``).

What it gives is the visible surface of whatever lies in the box — an occluder in front
of the box is left out, since its points fall outside the box.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from phirie_jax.io.atomic import write_files
from phirie_jax.observe.masks import camera_problem
from phirie_jax.observe.raycast import pixel_grid, pixel_rays
from phirie_jax.types import Camera, GaussianSplatData

MIN_ALPHA = 0.5  # a pixel with less accumulated opacity shows mostly nothing: no depth to trust


@dataclasses.dataclass(frozen=True)
class BoxPrompt:
    """One instance: the box ``lower`` (3,) … ``upper`` (3,), axis-aligned in the capture frame,
    or in the frame x_b = rotation @ x_c when ``rotation`` (3 × 3 nested tuples) is given."""

    id: int
    lower: tuple[float, float, float]
    upper: tuple[float, float, float]
    rotation: tuple[tuple[float, float, float], ...] | None = None

    def __post_init__(self):
        if not 0 < int(self.id) < 65536:
            raise ValueError(f"box prompt id {self.id}: expected 1 … 65535 (a 16-bit mask value, 0 = none)")
        lo, hi = np.asarray(self.lower, np.float64), np.asarray(self.upper, np.float64)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo)) or not np.all(np.isfinite(hi)):
            raise ValueError(f"box prompt {self.id}: expected finite 3-vectors, got {self.lower}, {self.upper}")
        if np.any(hi <= lo):
            raise ValueError(f"box prompt {self.id}: upper {tuple(hi)} must exceed lower {tuple(lo)} on every axis")
        if self.rotation is not None:
            rot = np.asarray(self.rotation, np.float64)
            if rot.shape != (3, 3) or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6) or np.linalg.det(rot) < 0:
                raise ValueError(f"box prompt {self.id}: rotation must be a 3×3 proper rotation matrix")

    @staticmethod
    def from_corners(instance_id: int, corners: Sequence[float]) -> "BoxPrompt":
        """From ``x0 y0 z0 x1 y1 z1`` (the two corners in any order)."""
        c = np.asarray(corners, np.float64).reshape(2, 3)
        return BoxPrompt(int(instance_id), tuple(c.min(0).tolist()), tuple(c.max(0).tolist()))

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: which of the points (N, 3) (capture frame) lie in the box (faces included)."""
        lo, hi = np.asarray(self.lower), np.asarray(self.upper)
        if self.rotation is not None:
            points = points @ np.asarray(self.rotation, np.float64).T
        return np.all((points >= lo) & (points <= hi), axis=-1)


@dataclasses.dataclass(frozen=True)
class BoxMaskConfig:
    """How box-prompt masks are made.

    Attributes:
        min_alpha: pixels with less rendered alpha get no label (their depth is mostly void).
        open_px: side of the square kernel of the morphological open (0 or 1 = none).
        close_px: side of the square kernel of the morphological close after it (0 or 1 = none).
        min_component: connected pieces of an id smaller than this fraction of its largest piece
            are dropped (haze in front of a wall lands in the box in patches); 0 keeps all.
    """

    min_alpha: float = MIN_ALPHA
    open_px: int = 3
    close_px: int = 5
    min_component: float = 0.2


@dataclasses.dataclass(frozen=True)
class BoxMaskResult:
    """What ``write_box_masks`` wrote: per camera (in the cameras' order) the mask path (or
    None where the camera could not be used) and each id's pixel count there."""

    paths: tuple[Path | None, ...]
    pixels: tuple[dict[int, int], ...]
    failures: tuple[dict, ...]

    def views_with(self, instance_id: int) -> int:
        return sum(1 for p in self.pixels if p.get(instance_id, 0) > 0)


def box_labels(depth: np.ndarray, alpha: np.ndarray, camera: Camera, boxes: Sequence[BoxPrompt],
               config: BoxMaskConfig = BoxMaskConfig()) -> np.ndarray:
    """(H, W) uint16 labels of one view from its rendered depth (H, W) (alpha-normalized, camera z)
    and alpha (H, W): the first box holding each opaque pixel's 3D point, cleaned per id."""
    height, width = camera.height, camera.width
    if depth.shape != (height, width) or alpha.shape != (height, width):
        raise ValueError(f"depth {depth.shape} and alpha {alpha.shape}: expected ({height}, {width}) "
                         f"like camera '{camera.name}'")
    rows, cols = pixel_grid(width, height)
    origins, dirs = pixel_rays(camera, rows, cols)
    d, a = depth.reshape(-1), alpha.reshape(-1)
    opaque = (a >= config.min_alpha) & (d > 0)
    points = origins[opaque] + d[opaque, None] * dirs[opaque]
    flat = np.zeros(height * width, np.uint16)
    where = np.flatnonzero(opaque)
    for box in boxes:
        inside = box.contains(points) & (flat[where] == 0)  # the first box given keeps a pixel
        flat[where[inside]] = box.id
    return clean_labels(flat.reshape(height, width), [b.id for b in boxes], config.open_px, config.close_px,
                        config.min_component)


def clean_labels(labels: np.ndarray, ids: Sequence[int], open_px: int, close_px: int, min_component: float
                 ) -> np.ndarray:
    """(H, W) uint16 ``labels`` with each id's pixels opened (specks of floaters and needles) and
    closed (pinholes) by square kernels of these sides (≤ 1: not), and its pieces smaller than
    ``min_component`` × its largest dropped; where cleaned ids overlap, the first in ``ids`` wins."""
    import cv2

    out = np.zeros_like(labels)
    for ident in ids:
        binary = (labels == ident).astype(np.uint8)
        if open_px > 1:
            binary = cv2.morphologyEx(binary, cv2.MORPH_OPEN, np.ones((open_px,) * 2, np.uint8))
        if close_px > 1:
            binary = cv2.morphologyEx(binary, cv2.MORPH_CLOSE, np.ones((close_px,) * 2, np.uint8))
        if min_component > 0 and binary.any():
            count, pieces, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
            area = stats[1:, cv2.CC_STAT_AREA]
            keep = np.flatnonzero(area >= min_component * area.max()) + 1
            binary = np.isin(pieces, keep).astype(np.uint8)
        out[(binary > 0) & (out == 0)] = ident
    return out


def box_masks(gaussians: GaussianSplatData, cameras: Sequence[Camera], boxes: Sequence[BoxPrompt],
              config: BoxMaskConfig = BoxMaskConfig()):
    """Yield (camera index, labels (H, W) uint16, or a reason string) for each camera."""
    from phirie_jax.render import prepared, render

    if not boxes:
        raise ValueError("no box prompts given (expected at least one)")
    ids = [b.id for b in boxes]
    if len(set(ids)) != len(ids):
        raise ValueError(f"box prompt ids {ids}: expected each id once")
    g = prepared(gaussians.to_host_kernel())
    for view, cam in enumerate(cameras):
        problem = camera_problem(cam)
        if problem is None:
            try:
                out = render(g, cam)
            except RuntimeError as err:  # the scene does not fit the renderer's buffers
                problem = f"render failed: {err}"
        if problem:
            yield view, problem
            continue
        yield view, box_labels(np.asarray(out.depth_normalized, np.float64), np.asarray(out.alpha, np.float64),
                               cam, boxes, config)


def encode_png(labels: np.ndarray) -> bytes:
    """16-bit PNG bytes of labels (H, W)."""
    import cv2

    ok, buf = cv2.imencode(".png", labels.astype(np.uint16))
    if not ok:
        raise RuntimeError("PNG encoding of a label image failed")
    return buf.tobytes()


def write_box_masks(gaussians: GaussianSplatData, cameras: Sequence[Camera], boxes: Sequence[BoxPrompt],
                    folder: str | Path, config: BoxMaskConfig = BoxMaskConfig()) -> BoxMaskResult:
    """Write ``folder/<image stem>.png`` for every usable camera (all staged, then renamed)."""
    folder = Path(folder)
    stems = [Path(c.name).stem for c in cameras]
    if len(set(stems)) != len(stems):
        raise ValueError("cameras share an image stem: their masks would overwrite each other")
    files, paths, pixels, failures = {}, [None] * len(cameras), [{} for _ in cameras], []
    for view, labels in box_masks(gaussians, cameras, boxes, config):
        if isinstance(labels, str):
            failures.append({"view": view, "path": cameras[view].name, "reason": labels})
            continue
        name = f"{stems[view]}.png"
        files[name] = encode_png(labels)
        paths[view] = folder / name
        ids, counts = np.unique(labels[labels > 0], return_counts=True)
        pixels[view] = {int(i): int(c) for i, c in zip(ids, counts)}
    write_files(folder, files)
    return BoxMaskResult(tuple(paths), tuple(pixels), tuple(failures))
