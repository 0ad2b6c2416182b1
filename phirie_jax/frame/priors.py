"""Metres per capture unit when nothing measured them: priors fitted to the capture's geometry.

Each prior is a typical length of one kind of capture with a band that holds the captures of
that kind (the truth lies within [s / f, s · f]); the most specific one that applies is used:

- a support over a visible floor (two horizontal planes, every camera above both, the
  support at 0.3–0.9 of the cameras' height over the floor): the support's height over the
  floor is ``SUPPORT_HEIGHT_M`` (desks and tables 0.70–0.78 m, counters 0.9 m, beds
  0.5–0.6 m);
- an object-centric orbit (the cameras' axes meet at a point): the cameras' median distance
  to it is ``ORBIT_DISTANCE_M`` (a phone around a mug on a desk is 0.2 m from it, around a
  large plush 0.8 m, around a table of objects 1.2 m: geometry alone cannot tell them apart);
- a support alone: the cameras' median height over it is ``CAMERA_HEIGHT_M`` (hand-held
  over a desk or a bed);
- else (a walk through a room, a wall): the cameras' median distance to what they see is
  ``VIEW_DISTANCE_M``.
Every source this returns starts with "prior:", so the frame line says so.
"""

from __future__ import annotations

import numpy as np

from phirie_jax.frame.estimate import Plane, angle_deg
from phirie_jax.frame.orbit import Orbit
from phirie_jax.types import Camera

SUPPORT_HEIGHT_M, SUPPORT_HEIGHT_BAND = 0.7, 1.35      # 0.52–0.95 m
ORBIT_DISTANCE_M, ORBIT_DISTANCE_BAND = 0.5, 2.5        # 0.2–1.25 m
CAMERA_HEIGHT_M, CAMERA_HEIGHT_BAND = 0.4, 2.0          # 0.2–0.8 m
VIEW_DISTANCE_M, VIEW_DISTANCE_BAND = 1.2, 2.5          # 0.48–3 m
SUPPORT_TO_CAMERA_HEIGHT = (0.3, 0.9)  # a support sits this fraction of the cameras' height over the floor
PARALLEL_DEG = 5.0
MIN_FLOOR_SHARE = 0.03   # a floor's level holds this share of the points (a room's clutter does not)


def find_floor(points: np.ndarray, support: Plane, up: np.ndarray, cameras: tuple[Camera, ...],
               threshold: float) -> Plane | None:
    """The densest level of the (P, 3) ``points`` at the heights a floor under ``support`` can
    have (the support 0.3–0.9 of the cameras' height over it), fitted as a plane parallel to up
    that no camera stands below; None when no level holds ``MIN_FLOOR_SHARE`` of the points.
    (Sequential RANSAC may spend its planes on the pieces of a rough support first.)"""
    from phirie_jax.frame.estimate import BELOW_TOLERANCE, dot

    if not len(points) or not cameras:
        return None
    heights = dot(points, up)
    top = float(up @ support.centroid)
    camera_height = float(np.median([c.center @ up for c in cameras]))
    if camera_height <= top:
        return None
    low, high = SUPPORT_TO_CAMERA_HEIGHT
    lowest, highest = (top - high * camera_height) / (1 - high), (top - low * camera_height) / (1 - low)
    width = 2 * threshold
    edges = np.arange(lowest, highest + width, width)
    if len(edges) < 2:
        return None
    counts, _ = np.histogram(heights, bins=edges)
    best = int(np.argmax(counts))
    if counts[best] < MIN_FLOOR_SHARE * len(points):
        return None
    level = 0.5 * (edges[best] + edges[best + 1])
    near = points[np.abs(heights - level) < threshold]
    centre = near.mean(0)
    normal = np.linalg.svd(near - centre, full_matrices=False)[2][-1]
    normal = normal if normal @ up >= 0 else -normal
    if angle_deg(normal, up) > PARALLEL_DEG:
        return None
    offset = float(normal @ centre)
    below = int(sum(c.center @ normal - offset < -BELOW_TOLERANCE * threshold for c in cameras))
    if below:
        return None
    return Plane(normal, offset, len(near), len(near) / len(points), "floor", 0, near[:2000])


def floor_under(support: Plane, planes: list[Plane], up: np.ndarray, camera_height: float) -> Plane | None:
    """The largest plane parallel to ``support`` that no camera stands below and that lies so far
    below it that the support sits ``SUPPORT_TO_CAMERA_HEIGHT`` of the cameras' height over it."""
    low, high = SUPPORT_TO_CAMERA_HEIGHT
    top = float(up @ support.centroid)
    floors = []
    for p in planes:
        level = float(up @ p.centroid)
        if p is support or p.cameras_below or angle_deg(p.normal, up) > PARALLEL_DEG or camera_height <= level:
            continue
        if low <= (top - level) / (camera_height - level) <= high:
            floors.append(p)
    return max(floors, key=lambda p: p.inliers) if floors else None


def scale_prior(support: Plane | None, planes: list[Plane], up: np.ndarray, cameras: tuple[Camera, ...],
                orbit: Orbit | None, distance: float) -> tuple[float, str, float, dict]:
    """(metres per capture unit, its source, ×/÷ band, what was measured)."""
    camera_height = float(np.median([c.center @ up for c in cameras]))
    if support is not None:
        floor = floor_under(support, planes, up, camera_height)
        if floor is not None:
            rise = float(up @ (support.centroid - floor.centroid))
            source = (f"prior: the support {rise:.4g} units over the floor, supports (tables, desks, beds) stand "
                      f"{SUPPORT_HEIGHT_M / SUPPORT_HEIGHT_BAND:.2g}–{SUPPORT_HEIGHT_M * SUPPORT_HEIGHT_BAND:.2g} m high")
            return SUPPORT_HEIGHT_M / rise, source, SUPPORT_HEIGHT_BAND, {"kind": "support over floor", "units": rise}
    if orbit is not None and orbit.is_orbit:
        source = (f"prior: the cameras orbit a point {orbit.distance:.4g} units away, object-centric captures are "
                  f"{ORBIT_DISTANCE_M / ORBIT_DISTANCE_BAND:.2g}–{ORBIT_DISTANCE_M * ORBIT_DISTANCE_BAND:.2g} m "
                  "from their object")
        return (ORBIT_DISTANCE_M / orbit.distance, source, ORBIT_DISTANCE_BAND,
                {"kind": "orbit distance", "units": orbit.distance})
    if support is not None:
        height = camera_height - float(up @ support.centroid)
        if height > 0:
            source = (f"prior: the cameras {height:.4g} units over the support, hand-held cameras are "
                      f"{CAMERA_HEIGHT_M / CAMERA_HEIGHT_BAND:.2g}–{CAMERA_HEIGHT_M * CAMERA_HEIGHT_BAND:.2g} m over it")
            return CAMERA_HEIGHT_M / height, source, CAMERA_HEIGHT_BAND, {"kind": "camera height", "units": height}
    source = (f"prior: the cameras {distance:.4g} units from what they see, hand-held captures of rooms and walls "
              f"are {VIEW_DISTANCE_M / VIEW_DISTANCE_BAND:.2g}–{VIEW_DISTANCE_M * VIEW_DISTANCE_BAND:.2g} m from it")
    return VIEW_DISTANCE_M / distance, source, VIEW_DISTANCE_BAND, {"kind": "view distance", "units": distance}
