"""The geometry of an object-centric capture: cameras that look at a common point.

The point is the least-squares meeting point of the cameras' optical axes. The capture is an
orbit when the axes pass close to it (median miss under ``MAX_MISS`` of the cameras' median
distance to it) and it lies in front of the cameras; it surrounds the point when the cameras'
directions from it leave no gap wider than ``MAX_GAP_DEG`` around up. A surrounding orbit
has its own up: the direction along which the cameras' unit directions from the point vary
least (rings and domes are level), signed towards the cameras' side. The point also says
where the support is: under it, with every camera above it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from phirie_jax.types import Camera

MAX_MISS = 0.25        # median axis-to-point distance / median camera distance
MIN_IN_FRONT = 0.9     # share of cameras that have the point in front of them
MAX_GAP_DEG = 120.0    # the widest empty sector of camera azimuths around up of a surrounding orbit
MAX_FLATNESS = 0.5     # least / middle variance of the camera directions for a ring's up
SIGMA_DEG = 8.0        # a surrounding orbit's up: hand-held rings tilt by several degrees


@dataclasses.dataclass(frozen=True)
class Orbit:
    centre: np.ndarray   # (3,) where the optical axes meet
    distance: float      # the cameras' median distance to it (capture units)
    miss: float          # median axis-to-point distance / distance
    in_front: float      # share of cameras with the point in front
    widest_gap_deg: float  # the widest empty azimuth sector around the reference up
    up: np.ndarray | None  # (3,) a surrounding orbit's up, else None

    @property
    def is_orbit(self) -> bool:
        return self.miss <= MAX_MISS and self.in_front >= MIN_IN_FRONT

    @property
    def surrounds(self) -> bool:
        return self.is_orbit and self.widest_gap_deg <= MAX_GAP_DEG

    def as_dict(self) -> dict:
        return {"centre": self.centre.round(6).tolist(), "distance": round(self.distance, 6),
                "miss": round(self.miss, 4), "in_front": round(self.in_front, 3),
                "widest_gap_deg": round(self.widest_gap_deg, 1), "is_orbit": self.is_orbit,
                "surrounds": self.surrounds, "up": None if self.up is None else self.up.round(6).tolist()}


def orbit(cameras: tuple[Camera, ...], reference_up: np.ndarray) -> Orbit | None:
    """The cameras' orbit geometry (None for fewer than 3 cameras or parallel axes);
    ``reference_up`` (3,) orders the azimuths."""
    if len(cameras) < 3:
        return None
    centres = np.array([c.center for c in cameras])
    axes = np.array([c.world_to_camera[2, :3] for c in cameras])
    projectors = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    system, rhs = projectors.sum(0), np.einsum("kij,kj->i", projectors, centres)
    if np.linalg.cond(system) > 1e8:
        return None
    point = np.linalg.solve(system, rhs)
    offsets = point - centres
    distances = np.linalg.norm(offsets, axis=1)
    distance = float(np.median(distances))
    miss = float(np.median(np.linalg.norm(np.einsum("kij,kj->ki", projectors, offsets), axis=1))) / max(distance, 1e-12)
    in_front = float(np.mean(np.einsum("kc,kc->k", offsets, axes) > 0))
    directions = -offsets / np.maximum(distances[:, None], 1e-12)
    gap = widest_gap_deg(directions, reference_up)
    up = None
    values, vectors = np.linalg.eigh(np.cov(directions.T))
    if gap <= MAX_GAP_DEG and values[0] <= MAX_FLATNESS * values[1]:
        up = vectors[:, 0] * (1.0 if vectors[:, 0] @ directions.mean(0) >= 0 else -1.0)
    return Orbit(point, distance, miss, in_front, gap, up)


def widest_gap_deg(directions: np.ndarray, up: np.ndarray) -> float:
    """The widest empty sector (degrees) of the (K, 3) directions' azimuths around ``up``."""
    up = up / np.linalg.norm(up)
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    azimuth = np.sort(np.degrees(np.arctan2(directions @ e2, directions @ e1)))
    gaps = np.diff(np.r_[azimuth, azimuth[0] + 360.0])
    return float(gaps.max())
