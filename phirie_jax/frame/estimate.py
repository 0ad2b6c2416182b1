"""Estimates of a capture's up and of metres per capture unit, from its Gaussians and cameras.

Up: the normal of the dominant support plane (RANSAC on the opaque Gaussian centres the
cameras see, oriented towards the cameras) when it agrees with the cameras' image-up votes
to within ``MAX_UP_DISAGREEMENT_DEG``; else the votes alone. The votes: the direction most
orthogonal to every camera's x axis (people hold cameras level), signed like their mean
image up; when the cameras barely turn, their mean image up made orthogonal to their x axis.

Scale (every prior stated, each with a multiplicative uncertainty: the truth lies within
[s / f, s · f]):
- a table top over a visible floor: the two largest horizontal planes ``TABLE_HEIGHT_M`` apart;
- else one support: the cameras' median height over it is ``CAMERA_HEIGHT_M`` (hand-held
  captures of things on a table or desk);
- else no support: the cameras' median distance to what they see is ``CAMERA_DISTANCE_M``.
Plane thresholds are fractions of the cameras' distance to the scene, so no estimate
assumes the capture's units.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from phirie_jax.geometry import sigmoid
from phirie_jax.types import Camera, GaussianSplatData

MAX_UP_DISAGREEMENT_DEG = 30.0  # a support plane must agree this well with the cameras' up votes
PARALLEL_DEG = 5.0              # planes this close in normal are the same orientation
TABLE_HEIGHT_M, TABLE_UNCERTAINTY = 0.74, 1.1    # tables and desks: 0.70–0.78 m
CAMERA_HEIGHT_M, CAMERA_HEIGHT_UNCERTAINTY = 0.4, 2.0      # hand-held, above a table top
CAMERA_DISTANCE_M, CAMERA_DISTANCE_UNCERTAINTY = 0.6, 2.5  # hand-held, around an object
TABLE_TO_CAMERA_HEIGHT = (0.3, 0.9)  # a table top sits this fraction of the cameras' height over the floor
PLANE_THRESHOLD = 0.01   # RANSAC inlier distance, as a fraction of the camera-to-scene distance
MIN_PLANE_SHARE = 0.05   # a plane holds at least this share of the sampled centres
MAX_PLANES = 4
MAX_SAMPLES = 30_000     # opaque centres sampled for the estimates
MIN_OPACITY = 0.5
HYPOTHESES = 256


@dataclasses.dataclass(frozen=True)
class Plane:
    normal: np.ndarray  # (3,) unit, pointing to the side most cameras are on
    offset: float       # normal · x = offset on the plane
    inliers: int
    share: float        # inliers / sampled centres

    def as_dict(self) -> dict:
        return {"normal": self.normal.round(6).tolist(), "offset": round(self.offset, 6),
                "inliers": self.inliers, "share": round(self.share, 4)}


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two (3,) directions."""
    c = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def cameras_up(cameras: tuple[Camera, ...] | list[Camera]) -> np.ndarray:
    """(3,) the cameras' up vote (see the module docstring); +z without cameras."""
    if not cameras:
        return np.array([0.0, 0.0, 1.0])
    rights = np.array([c.world_to_camera[0, :3] for c in cameras])
    mean_up = -np.mean([c.world_to_camera[1, :3] for c in cameras], axis=0)
    mean_up /= max(np.linalg.norm(mean_up), 1e-12)
    values, vectors = np.linalg.eigh(rights.T @ rights / len(rights))
    if values[1] > 0.05 * values[2]:
        up = vectors[:, 0]
    else:
        axis = vectors[:, 2]
        up = mean_up - (mean_up @ axis) * axis
    up = up / max(np.linalg.norm(up), 1e-12)
    return up if up @ mean_up >= 0 else -up


def visible_centres(gaussians: GaussianSplatData, cameras: tuple[Camera, ...], rng: np.random.Generator
                    ) -> tuple[np.ndarray, float]:
    """Up to ``MAX_SAMPLES`` opaque Gaussian centres (P, 3) inside some camera's view, and the
    cameras' median distance to what they see (median over cameras of the median depth)."""
    opaque = gaussians.means[sigmoid(gaussians.opacity_logits) >= MIN_OPACITY].astype(np.float64)
    if len(opaque) > 4 * MAX_SAMPLES:
        opaque = opaque[rng.choice(len(opaque), 4 * MAX_SAMPLES, replace=False)]
    seen = np.zeros(len(opaque), bool)
    depths = []
    for cam in cameras:
        uv, depth = cam.project(opaque)
        inside = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        if inside.any():
            depths.append(float(np.median(depth[inside])))
            seen |= inside
    if not depths:
        raise ValueError("no opaque Gaussian is in front of any camera")
    points = opaque[seen]
    if len(points) > MAX_SAMPLES:
        points = points[rng.choice(len(points), MAX_SAMPLES, replace=False)]
    return points, float(np.median(depths))


def find_planes(points: np.ndarray, threshold: float, rng: np.random.Generator) -> list[tuple[np.ndarray, float, int]]:
    """Up to ``MAX_PLANES`` planes of (P, 3) points, largest first, by sequential RANSAC with a
    least-squares refit: (normal (3,), offset, inliers) each, unoriented."""
    remaining, total, planes = points, len(points), []
    for _ in range(MAX_PLANES):
        if len(remaining) < max(3, MIN_PLANE_SHARE * total):
            break
        a, b, c = (remaining[rng.integers(0, len(remaining), HYPOTHESES)] for _ in range(3))
        normals = np.cross(b - a, c - a)
        length = np.linalg.norm(normals, axis=1)
        normals = normals[length > 0] / length[length > 0, None]
        if not len(normals):
            break
        offsets = np.einsum("hc,hc->h", normals, a[length > 0])
        counts = (np.abs(remaining @ normals.T - offsets) < threshold).sum(0)
        normal, offset = normals[np.argmax(counts)], offsets[np.argmax(counts)]
        inliers = np.abs(remaining @ normal - offset) < threshold
        for _ in range(2):  # least-squares refit on the inliers
            centre = remaining[inliers].mean(0)
            normal = np.linalg.svd(remaining[inliers] - centre, full_matrices=False)[2][-1]
            offset = float(normal @ centre)
            inliers = np.abs(remaining @ normal - offset) < threshold
        if inliers.sum() < MIN_PLANE_SHARE * total:
            break
        planes.append((normal, offset, int(inliers.sum())))
        remaining = remaining[~inliers]
    return planes


def oriented_planes(planes, cameras: tuple[Camera, ...], total: int) -> list[Plane]:
    """Each plane's normal turned towards the side most camera centres are on."""
    centres = np.array([c.center for c in cameras]).reshape(-1, 3)
    out = []
    for normal, offset, inliers in planes:
        if len(centres) and np.median(centres @ normal - offset) < 0:
            normal, offset = -normal, -offset
        out.append(Plane(normal, float(offset), inliers, inliers / max(total, 1)))
    return out


def estimate_up(planes: list[Plane], cameras: tuple[Camera, ...]) -> tuple[np.ndarray, str]:
    """(3,) up and where it came from."""
    votes = cameras_up(cameras)
    agreeing = [p for p in planes if angle_deg(p.normal, votes) <= MAX_UP_DISAGREEMENT_DEG]
    if not agreeing:
        return votes, f"cameras' image up ({len(cameras)} cameras; no support plane within " \
                      f"{MAX_UP_DISAGREEMENT_DEG:.0f}° of it)"
    best = max(agreeing, key=lambda p: p.inliers)
    parallel = [p for p in agreeing if angle_deg(p.normal, best.normal) <= PARALLEL_DEG]
    up = np.sum([p.normal * p.inliers for p in parallel], axis=0)
    up /= np.linalg.norm(up)
    return up, (f"support plane ({len(parallel)} parallel plane(s), {sum(p.inliers for p in parallel)} "
                f"Gaussian centres), {angle_deg(up, votes):.1f}° from the cameras' image up")


def estimate_scale(planes: list[Plane], up: np.ndarray, cameras: tuple[Camera, ...], distance: float
                   ) -> tuple[float, str, float]:
    """(metres per capture unit, where it came from, multiplicative uncertainty)."""
    horizontal = sorted((p for p in planes if angle_deg(p.normal, up) <= PARALLEL_DEG), key=lambda p: p.offset)
    camera_heights = np.array([c.center @ up for c in cameras])
    if len(horizontal) >= 2:
        floor, table = horizontal[0], max(horizontal[1:], key=lambda p: p.inliers)
        rise, over_floor = table.offset - floor.offset, float(np.median(camera_heights)) - floor.offset
        low, high = TABLE_TO_CAMERA_HEIGHT
        if over_floor > 0 and low <= rise / over_floor <= high:
            return (TABLE_HEIGHT_M / rise, f"table top {rise:.4g} units over the floor (prior {TABLE_HEIGHT_M} m)",
                    TABLE_UNCERTAINTY)
    if horizontal:
        support = max(horizontal, key=lambda p: p.inliers)
        height = float(np.median(camera_heights)) - support.offset
        if height > 0:
            return (CAMERA_HEIGHT_M / height, f"cameras {height:.4g} units over the support (hand-held prior "
                    f"{CAMERA_HEIGHT_M} m)", CAMERA_HEIGHT_UNCERTAINTY)
    return (CAMERA_DISTANCE_M / distance, f"cameras {distance:.4g} units from what they see (hand-held prior "
            f"{CAMERA_DISTANCE_M} m)", CAMERA_DISTANCE_UNCERTAINTY)
