"""Each instance's support plane, in the scene's gravity frame (``phirie_jax.frame.gravity``).

The observation stage finds it once (its points on the plane are not the object's, see
``ObserveConfig.support_clearance``) and records it with the instance; later stages read it
(``Support.from_record``).

Support of an instance: rays cast straight down onto the scene surface around its
footprint (a ring 1.5–6 cm outside Q's robust box) hit what it stands on. Of the hits
no higher than 1 cm above Q's 2nd-percentile height and at most ``MAX_HIDDEN_BASE``
below it (the lower part of a round object is often never seen), the densest 5 mm
height bin wins and the support is the median of the hits within 1 cm of it. Without a
surface (or hits), the support is Q's 2nd-percentile height and says so.

A ``Wall`` is a near-vertical plane of the background the instance stands in front of (found
behind a prompt's object, ``observe.prompt_masks.prompt_walls``): what a mounted object (a head
on a wall, a shelf-mounted box) is held by when nothing is under it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from phirie_jax.frame.gravity import GravityFrame

RING_INNER, RING_OUTER = 0.015, 0.06   # ring around the footprint, metres
RING_RAYS = 24                         # rays per side of the ring's sampling grid
ABOVE_BASE = 0.01                      # hits up to this above Q's base height count
MAX_HIDDEN_BASE = 0.15                 # ... and down to this below it
HEIGHT_BIN = 0.005                     # the support is the densest bin of hit heights
SUPPORT_BAND = 0.01                    # hits within this of that bin are the support's
MIN_PLANE_HITS = 20                    # support hits needed to fit the support's normal


@dataclasses.dataclass(frozen=True)
class Support:
    height: float         # support plane height in the gravity frame
    source: str           # "surface" (rays onto the scene surface), "prompt" (found under a prompt's
                          # object: ``PromptMasks.supports``) or "observed points"
    hits: int             # rays that hit the support
    normal: np.ndarray    # (3,) gravity-frame normal of the fitted plane (+z without a fit)
    clearance: float | None = None  # Q_i's points less than this above the support were cut
                                    # (``ObserveConfig.support_clearance``); None: nothing was

    @property
    def is_plane(self) -> bool:
        """Found on the scene surface by enough rays to be a plane under the object (a few hits
        on a wall-mounted object's plaque or a neighbour are not one), or under a prompt's object
        by enough flat, up-facing Gaussians."""
        return self.source in ("surface", "prompt") and self.hits >= MIN_PLANE_HITS

    def as_record(self) -> dict:
        cut = {} if self.clearance is None else {"clearance": self.clearance}
        return {"height": round(self.height, 6), "source": self.source, "hits": self.hits,
                "normal": np.round(self.normal, 6).tolist(), **cut}

    @staticmethod
    def from_record(record: dict) -> Support:
        clearance = record.get("clearance")
        return Support(float(record["height"]), str(record["source"]), int(record["hits"]),
                       np.asarray(record["normal"], np.float64), None if clearance is None else float(clearance))


WALL_TILT_DEG = 20.0    # a wall's normal is within this of horizontal


@dataclasses.dataclass(frozen=True)
class Wall:
    """A near-vertical background plane behind an instance, in the world frame: points x with
    ``normal · x = offset`` (normal towards the instance)."""

    normal: np.ndarray    # (3,) unit, world frame
    offset: float
    gap: float            # the instance's Gaussians' 2nd-percentile distance in front of it, metres
    source: str           # where it was found, for people

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(N,) signed distance of world ``points`` (N, 3) in front of the wall."""
        return np.asarray(points, np.float64) @ self.normal - self.offset

    def in_frame(self, rotation: np.ndarray) -> Wall:
        """The wall in a frame rotated by ``rotation`` (3, 3) about the origin (x' = R x)."""
        return dataclasses.replace(self, normal=np.asarray(rotation, np.float64) @ self.normal)

    def as_record(self) -> dict:
        return {"normal": np.round(self.normal, 6).tolist(), "offset": round(self.offset, 6),
                "gap_m": round(self.gap, 4), "source": self.source}

    @staticmethod
    def from_record(record: dict | None) -> Wall | None:
        if not record:
            return None
        return Wall(np.asarray(record["normal"], np.float64), float(record["offset"]), float(record["gap_m"]),
                    str(record["source"]))


def is_wall(normal: np.ndarray, up=(0.0, 0.0, 1.0)) -> bool:
    """Whether a plane with this ``normal`` (3,) is near-vertical (``WALL_TILT_DEG``)."""
    normal = np.asarray(normal, np.float64)
    return abs(float(normal @ np.asarray(up, np.float64))) <= np.sin(np.radians(WALL_TILT_DEG)) * np.linalg.norm(normal)


def _ring_origins(q_gravity: np.ndarray) -> np.ndarray:
    lo, hi = np.percentile(q_gravity, [2, 98], axis=0)
    xs = np.linspace(lo[0] - RING_OUTER, hi[0] + RING_OUTER, RING_RAYS)
    ys = np.linspace(lo[1] - RING_OUTER, hi[1] + RING_OUTER, RING_RAYS)
    xx, yy = np.meshgrid(xs, ys, indexing="ij")
    xy = np.stack([xx.ravel(), yy.ravel()], 1)
    outside = np.any((xy < lo[:2] - RING_INNER) | (xy > hi[:2] + RING_INNER), axis=1)
    xy = xy[outside]
    return np.concatenate([xy, np.full((len(xy), 1), hi[2] + 0.1)], axis=1)


def find_support(q_gravity: np.ndarray, frame: GravityFrame, raycaster=None) -> Support:
    """The plane instance Q stands on (see the module docstring)."""
    base = float(np.percentile(q_gravity[:, 2], 2))
    if raycaster is not None and len(q_gravity) >= 3:
        origins = _ring_origins(q_gravity)
        down = np.tile(frame.to_world(np.array([[0.0, 0.0, -1.0]])), (len(origins), 1))
        hits = raycaster.cast(frame.to_world(origins), down)
        points = frame.to_gravity(hits.points[hits.hit])
        below = points[(points[:, 2] <= base + ABOVE_BASE) & (points[:, 2] >= base - MAX_HIDDEN_BASE)]
        near = below[:0]
        if len(below):
            edges = np.arange(below[:, 2].min(), below[:, 2].max() + 2 * HEIGHT_BIN, HEIGHT_BIN)
            counts, edges = np.histogram(below[:, 2], bins=edges)
            mode = edges[np.argmax(counts)] + 0.5 * HEIGHT_BIN
            near = below[np.abs(below[:, 2] - mode) <= SUPPORT_BAND]
        if len(near):
            normal = np.array([0.0, 0.0, 1.0])
            if len(near) >= MIN_PLANE_HITS:
                centred = near - near.mean(0)
                normal = np.linalg.svd(centred, full_matrices=False)[2][-1]
                normal = normal if normal[2] > 0 else -normal
            return Support(float(np.median(near[:, 2])), "surface", len(near), normal)
    return Support(base, "observed points", 0, np.array([0.0, 0.0, 1.0]))
