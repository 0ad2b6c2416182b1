"""Plumb lines: the vertical direction the photos' straight edges agree on.

Door frames, wall corners, furniture and picture frames are built plumb, so their edges are
parallel to gravity. A straight edge seen in one photo spans a plane through that camera's
centre; every vertical edge's plane contains the vertical direction v, so v is the
direction orthogonal to all their normals (a vanishing point, found across every view at
once). Segments come from OpenCV's line segment detector on up to ``VIEWS`` photos; RANSAC
on pairs of segment planes near the cameras' level vote finds v, and a least-squares refit
on the segments within ``INLIER_DEG`` refines it. Enough of the near-vertical segments must
agree (``MIN_SHARE``: short random edges share some direction by chance): a capture without
plumb edges (a tabletop on a plain floor) has no such direction, and the cue says so.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from phirie_jax.threads import map_on_cores
from phirie_jax.types import Camera

VIEWS = 40
MAX_SIDE = 1280            # photos are read at most this large
MIN_LENGTH = 0.06          # segments at least this fraction of the photo's longer side
SEARCH_DEG = 30.0          # v is looked for this close to the cameras' level vote
INLIER_DEG = 1.0           # a segment's plane within this of containing v
MIN_SEGMENTS = 12
MIN_SHARE = 0.12           # of the near-vertical segments: random edges share a direction by chance
                           # (~9 % among clutter); plumb edges are 20–40 % of them in real rooms
MIN_VIEWS = 4
HYPOTHESES = 2000
MIN_SIGMA_DEG = 1.0        # edges are built plumb to about this


@dataclasses.dataclass(frozen=True)
class PlumbLines:
    up: np.ndarray          # (3,) unit, signed like the level vote
    segments: int           # inlier segments
    views: int              # photos they come from
    residual_deg: float     # median angle between v and the inlier segments' planes
    sigma_deg: float        # how far v may be off (≥ MIN_SIGMA_DEG)

    def as_dict(self) -> dict:
        return {"up": self.up.round(6).tolist(), "segments": self.segments, "views": self.views,
                "residual_deg": round(self.residual_deg, 3), "sigma_deg": round(self.sigma_deg, 3)}


def segment_normals(camera: Camera, segments: np.ndarray) -> np.ndarray:
    """(S, 3) world unit normals of the planes through ``camera``'s centre and its (S, 4)
    segments (x0, y0, x1, y1 in the photo's pixel coordinates, pixel centres at i + 0.5)."""
    rays = [normalized_rays(camera, segments[:, 2 * k: 2 * k + 2]) for k in (0, 1)]
    normals = np.cross(rays[0], rays[1]) @ camera.world_to_camera[:3, :3]  # camera → world: Rᵀ n
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)


def normalized_rays(camera: Camera, pixels: np.ndarray) -> np.ndarray:
    """(P, 3) camera-frame rays (z = 1) of (P, 2) pixel positions, the lens distortion undone."""
    pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
    if camera.is_distorted:
        import cv2

        k_cv = camera.K.copy()
        k_cv[:2, 2] -= 0.5  # OpenCV counts pixel centres at integers
        xy = cv2.undistortPoints((pixels - 0.5).reshape(-1, 1, 2), k_cv, camera.distortion).reshape(-1, 2)
    else:
        xy = (pixels - camera.K[:2, 2]) / np.diag(camera.K)[:2]
        xy[:, 0] -= camera.K[0, 1] * xy[:, 1] / camera.K[0, 0]
    return np.column_stack([xy, np.ones(len(xy))])


def detect_segments(camera: Camera) -> np.ndarray:
    """(S, 4) straight segments of ``camera``'s photo longer than ``MIN_LENGTH`` of its side, in
    its pixel coordinates (pixel centres at i + 0.5); empty when the photo cannot be read."""
    import cv2

    if camera.image_path is None:
        return np.zeros((0, 4))
    image = cv2.imread(str(camera.image_path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        return np.zeros((0, 4))
    factor = min(1.0, MAX_SIDE / max(image.shape))
    if factor < 1.0:
        image = cv2.resize(image, None, fx=factor, fy=factor, interpolation=cv2.INTER_AREA)
    found = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD).detect(image)[0]
    if found is None:
        return np.zeros((0, 4))
    segments = found.reshape(-1, 4).astype(np.float64)
    segments = segments[np.hypot(segments[:, 2] - segments[:, 0], segments[:, 3] - segments[:, 1])
                        >= MIN_LENGTH * max(image.shape)]
    # back to the camera's pixels (the photo may differ in size from the camera's record)
    return (segments + 0.5) * np.tile([camera.width / image.shape[1], camera.height / image.shape[0]], 2)


def plumb_lines(cameras: tuple[Camera, ...], vote: np.ndarray, rng: np.random.Generator) -> tuple[PlumbLines | None, str]:
    """The vertical the photos' edges agree on (None and why not, when they do not)."""
    from phirie_jax.frame.surface import view_indices

    normals, views = [], []
    chosen = view_indices(len(cameras), VIEWS)
    for i, segments in zip(chosen, map_on_cores(lambda i: detect_segments(cameras[i]), chosen, "straight edges")):
        if len(segments):
            normals.append(segment_normals(cameras[i], segments))
            views.append(np.full(len(segments), i))
    if not normals:
        return None, "no photo to read straight edges from"
    normals, views = np.concatenate(normals), np.concatenate(views)
    near = np.abs(normals @ vote) < np.sin(np.radians(SEARCH_DEG))
    normals, views = normals[near], views[near]
    if len(normals) < MIN_SEGMENTS:
        return None, f"{len(normals)} near-vertical straight edges in the photos (expected ≥ {MIN_SEGMENTS})"
    best, best_count = None, 0
    pairs = rng.integers(0, len(normals), (HYPOTHESES, 2))
    candidates = np.cross(normals[pairs[:, 0]], normals[pairs[:, 1]])
    length = np.linalg.norm(candidates, axis=1)
    ok = length > 0.1
    candidates = candidates[ok] / length[ok, None]
    candidates *= np.sign(candidates @ vote)[:, None]
    candidates = candidates[candidates @ vote >= np.cos(np.radians(SEARCH_DEG))]
    tolerance = np.sin(np.radians(INLIER_DEG))
    if len(candidates):
        counts = (np.abs(np.einsum("sc,hc->sh", normals, candidates)) < tolerance).sum(0)
        best, best_count = candidates[np.argmax(counts)], int(counts.max())
    if best is None or best_count < MIN_SEGMENTS:
        return None, f"at most {best_count} straight edges share a direction near the level vote (expected ≥ {MIN_SEGMENTS})"
    up = best
    for _ in range(3):
        inliers = np.abs(normals @ up) < tolerance
        values, vectors = np.linalg.eigh(normals[inliers].T @ normals[inliers])
        up = vectors[:, 0] * np.sign(vectors[:, 0] @ vote)
    inliers = np.abs(normals @ up) < tolerance
    seen = len(np.unique(views[inliers]))
    if inliers.sum() < max(MIN_SEGMENTS, MIN_SHARE * len(normals)) or seen < MIN_VIEWS:
        return None, (f"{int(inliers.sum())} of {len(normals)} near-vertical straight edges in {seen} photos share "
                      f"a direction (expected ≥ {MIN_SEGMENTS} and {MIN_SHARE:.0%} of them, in ≥ {MIN_VIEWS} photos)")
    residual = np.degrees(np.arcsin(np.abs(normals[inliers] @ up)))
    # how well the inlier planes pin v: their normals must spread in both directions ⟂ v
    values = np.linalg.eigvalsh(normals[inliers].T @ normals[inliers])
    spread = values[1] / max(values.sum(), 1e-12)
    sigma = np.degrees(np.radians(max(float(np.median(residual)), 0.05)) * 1.5 / np.sqrt(max(spread, 1e-6) * inliers.sum()))
    return PlumbLines(up, int(inliers.sum()), int(seen), float(np.median(residual)), max(MIN_SIGMA_DEG, float(sigma))), ""
