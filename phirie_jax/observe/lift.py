"""First-hit lifting: each (view, mask) becomes the surface points its pixels see.

For the mask pixels on a stride (away from other labels by ``mask_erosion_px``; on a photo
wider than ``working_width``, the pixels of the working image's stride), the ray
through the pixel centre meets the scene surface first at one point; that point is the
pixel's 3D observation. One ray cast per view serves all of its masks.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import ndimage

from phirie_jax.observe.config import ObserveConfig
from phirie_jax.observe.masks import ViewMasks
from phirie_jax.observe.raycast import Raycaster, pixel_rays, working_pixel_grid
from phirie_jax.types import Camera


@dataclasses.dataclass(frozen=True)
class Proposal:
    """One (view, mask) lifted onto the surface."""

    view: int
    label: int
    instance_id: int | None
    category: str | None
    score: float | None
    points: np.ndarray   # (P, 3) first-hit points of its strided pixels
    pixels: int          # full-resolution pixel count of the mask
    bbox: tuple[int, int, int, int]  # x0, y0, x1, y1 (inclusive) in pixels

    def summary(self) -> dict:
        return {"view": self.view, "label": self.label, "pixels": self.pixels,
                "lifted_points": len(self.points), "bbox": list(self.bbox), "score": self.score}


def interior(labels: np.ndarray, radius: int) -> np.ndarray:
    """(H, W) bool: labelled pixels whose (2r+1)² neighbourhood holds only their own label."""
    if radius == 0:
        return labels > 0
    size = 2 * radius + 1
    same = ndimage.minimum_filter(labels, size, mode="nearest") == ndimage.maximum_filter(labels, size, mode="nearest")
    return same & (labels > 0)


def lift_view(raycaster: Raycaster, camera: Camera, masks: ViewMasks, config: ObserveConfig
              ) -> tuple[list[Proposal], list[dict]]:
    """Proposals of one view and the segments rejected there (with their reasons)."""
    labels = masks.labels
    present, counts = np.unique(labels, return_counts=True)
    pixel_count = dict(zip(present.tolist(), counts.tolist()))
    rows, cols = working_pixel_grid(camera.width, camera.height, config.pixel_stride, config.working_width)
    sampled = labels[np.ix_(rows, cols)].ravel()
    usable = interior(labels, config.mask_erosion_px)[np.ix_(rows, cols)].ravel()
    origins, dirs = pixel_rays(camera, rows, cols)
    take = np.flatnonzero(usable)
    hits = raycaster.cast(origins[take], dirs[take])
    hit = hits.hit
    hit_labels, hit_points = sampled[take][hit], hits.points[hit]
    order = np.argsort(hit_labels, kind="stable")
    hit_labels, hit_points = hit_labels[order], hit_points[order]

    proposals, rejected = [], []
    for label, segment in sorted(masks.segments.items()):
        base = {"view": masks.view, "label": label, "instance_id": segment.instance_id}
        n_pixels = pixel_count.get(label, 0)
        if n_pixels == 0:
            rejected.append({**base, "reason": f"label {label} has no pixels in {masks.path}"})
            continue
        lo, hi = np.searchsorted(hit_labels, [label, label + 1])
        if hi - lo < config.min_proposal_points:
            rejected.append({**base, "reason": f"{hi - lo} lifted points (< {config.min_proposal_points}) "
                             f"from {n_pixels} pixels: too small or off the surface"})
            continue
        ys, xs = np.nonzero(labels == label)
        proposals.append(Proposal(masks.view, label, segment.instance_id, segment.category, segment.score,
                                  hit_points[lo:hi], n_pixels,
                                  (int(xs.min()), int(ys.min()), int(xs.max()), int(ys.max()))))
    return proposals, rejected


def silhouette_votes(points: list[np.ndarray], labels: list[int], camera: Camera, view_labels: np.ndarray
                     ) -> list[tuple[np.ndarray, np.ndarray]]:
    """One view's votes on several instances' points (``silhouette_agreement`` in the config):
    instance k's points ``points[k]`` (P_k, 3) and its value ``labels[k]`` in ``view_labels``
    (H, W). Returns per instance ((P_k,) bool: on its label, (P_k,) bool: counted — in front
    of the camera, in the image, on its label or on none)."""
    votes = []
    for pts, own in zip(points, labels, strict=True):
        inside = np.zeros(len(pts), bool)
        counted = np.zeros(len(pts), bool)
        if len(pts):
            uv, depth = camera.project(pts)
            col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
            ok = (depth > 0) & (col >= 0) & (row >= 0) & (col < view_labels.shape[1]) & (row < view_labels.shape[0])
            seen = np.full(len(pts), -1, np.int64)
            seen[ok] = view_labels[row[ok], col[ok]]
            inside = seen == own
            counted = inside | (seen == 0)
        votes.append((inside, counted))
    return votes
