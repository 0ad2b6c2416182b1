"""Low-level estimates from a capture's Gaussians and cameras: the cameras' level vote, the
opaque Gaussian centres they see, and planes of a point set (sequential RANSAC), each plane
oriented towards the cameras and told how many cameras stand below it.

The cameras' level vote: the direction most orthogonal to every camera's x axis (people hold
cameras level), signed like their mean image up; when the cameras barely turn, their mean
image up made orthogonal to their x axis. Plane thresholds are fractions of the cameras'
distance to the scene, so nothing here assumes the capture's units. How these become up and
metres: ``phirie_jax.frame.cues`` and ``phirie_jax.frame.priors``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from phirie_jax.geometry import sigmoid
from phirie_jax.types import Camera, GaussianSplatData

PLANE_THRESHOLD = 0.01   # RANSAC inlier distance, as a fraction of the camera-to-scene distance
BELOW_TOLERANCE = 2.0    # a camera this many inlier distances under a plane stands below it
MIN_PLANE_SHARE = 0.05   # a plane holds at least this share of the sampled points
MAX_PLANES = 4
MAX_SAMPLES = 30_000     # opaque centres sampled for the estimates
MIN_OPACITY = 0.5
HYPOTHESES = 256
KEPT_INLIERS = 2000      # inlier points a plane keeps for later tests (where it lies)
TURNING_CAMERAS = 0.05   # the vote's second eigenvalue share below which the cameras barely turn


@dataclasses.dataclass(frozen=True)
class Plane:
    normal: np.ndarray   # (3,) unit, pointing to the side most cameras are on
    offset: float        # normal · x = offset on the plane
    inliers: int
    share: float         # inliers / sampled points
    source: str = ""     # the points it was fitted to
    cameras_below: int = 0
    points: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)), repr=False)  # (≤2000, 3) inliers

    @property
    def centroid(self) -> np.ndarray:
        return self.points.mean(0) if len(self.points) else self.normal * self.offset

    def as_dict(self) -> dict:
        return {"source": self.source, "normal": self.normal.round(6).tolist(), "offset": round(self.offset, 6),
                "inliers": self.inliers, "share": round(self.share, 4), "cameras_below": self.cameras_below}


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two (3,) directions."""
    c = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def cameras_up(cameras: tuple[Camera, ...] | list[Camera]) -> np.ndarray:
    """(3,) the cameras' level vote (see the module docstring); +z without cameras."""
    return level_vote(cameras)[0]


def level_vote(cameras) -> tuple[np.ndarray, bool]:
    """(3,) the cameras' level vote and whether the cameras turn enough for the level rule
    (else the vote is their mean image up)."""
    if not cameras:
        return np.array([0.0, 0.0, 1.0]), False
    rights = np.array([c.world_to_camera[0, :3] for c in cameras])
    mean_up = -np.mean([c.world_to_camera[1, :3] for c in cameras], axis=0)
    mean_up /= max(np.linalg.norm(mean_up), 1e-12)
    values, vectors = np.linalg.eigh(rights.T @ rights / len(rights))
    turning = bool(values[1] > TURNING_CAMERAS * values[2])
    if turning:
        up = vectors[:, 0]
    else:
        axis = vectors[:, 2]
        up = mean_up - (mean_up @ axis) * axis
    up = up / max(np.linalg.norm(up), 1e-12)
    return (up if up @ mean_up >= 0 else -up), turning


def dot(points: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """(N,) dot products of (N, 3) points with a (3,) direction, without a threaded BLAS call."""
    return points[:, 0] * direction[0] + points[:, 1] * direction[1] + points[:, 2] * direction[2]


def project(camera: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Camera.project`` of (N, 3) points written out per coordinate: (N, 2) pixels, (N,) depth.
    (A (N, 3) × (3, 3) product through a threaded BLAS is ten times slower on a busy machine.)"""
    r, t, k = camera.world_to_camera[:3, :3], camera.world_to_camera[:3, 3], camera.K
    x, y, z = (points[:, 0] * r[i, 0] + points[:, 1] * r[i, 1] + points[:, 2] * r[i, 2] + t[i] for i in range(3))
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (k[0, 0] * x + k[0, 1] * y) / z + k[0, 2]
        v = k[1, 1] * y / z + k[1, 2]
    return np.stack([u, v], axis=1), z


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
        uv, depth = project(cam, opaque)
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


def find_planes(points: np.ndarray, threshold: float, rng: np.random.Generator
                ) -> list[tuple[np.ndarray, float, np.ndarray]]:
    """Up to ``MAX_PLANES`` planes of (P, 3) points, largest first, by sequential RANSAC with a
    least-squares refit: (normal (3,), offset, inlier points (M, 3)) each, unoriented."""
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
        counts = (np.abs(np.einsum("pc,hc->ph", remaining, normals) - offsets) < threshold).sum(0)
        normal, offset = normals[np.argmax(counts)], offsets[np.argmax(counts)]
        inliers = np.abs(dot(remaining, normal) - offset) < threshold
        for _ in range(2):  # least-squares refit on the inliers
            centre = remaining[inliers].mean(0)
            normal = np.linalg.svd(remaining[inliers] - centre, full_matrices=False)[2][-1]
            offset = float(normal @ centre)
            inliers = np.abs(dot(remaining, normal) - offset) < threshold
        if inliers.sum() < MIN_PLANE_SHARE * total:
            break
        planes.append((normal, offset, remaining[inliers]))
        remaining = remaining[~inliers]
    return planes


def oriented_planes(planes, cameras: tuple[Camera, ...], total: int, threshold: float = 0.0,
                    source: str = "", rng: np.random.Generator | None = None) -> list[Plane]:
    """Each plane's normal turned towards the side most camera centres are on, with the count of
    cameras more than ``BELOW_TOLERANCE`` × ``threshold`` below it."""
    centres = np.array([c.center for c in cameras]).reshape(-1, 3)
    rng = rng or np.random.default_rng(0)
    out = []
    for normal, offset, points in planes:
        if len(centres) and np.median(centres @ normal - offset) < 0:
            normal, offset = -normal, -offset
        below = int(np.sum(centres @ normal - offset < -BELOW_TOLERANCE * threshold)) if len(centres) else 0
        kept = points if len(points) <= KEPT_INLIERS else points[rng.choice(len(points), KEPT_INLIERS, replace=False)]
        out.append(Plane(normal, float(offset), len(points), len(points) / max(total, 1), source, below, kept))
    return out
