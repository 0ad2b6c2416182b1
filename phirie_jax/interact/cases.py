"""Procedural drop-test cases whose verdict physics decides: the agreement set of the tests and
of ``experiments/bench_droptest.py``. NumPy only (a benchmark machine may have nothing else).

Each case is a convex shape (box, cone, cylinder, thin plate), centred on its axis with its
base at z = 0, in an orientation whose verdict statics give ("expected"):

- stable: a box on any of its faces, a cone on its base, a cylinder upright or lying on a
  facet, a plate lying flat or standing on its edge tilted *within* its support, each with
  a few degrees of tilt that settling removes;
- unstable: a cone on its tip tilted 2–10°, a box balanced on one edge tilted 3–10° past
  balance, a thin plate standing on its edge tilted past its support, a tall cylinder on
  its rim tilted 25–40°; all sized so that toppling moves the centre of mass well over 3 cm.

The hard set (``hard_set``) is near the edges of the protocol instead: a box or a cone only
0.3–1.5° past balance (unstable, but it starts to fall only after the settling phase), and
small boxes toppling off an edge, whose drift lands around the 3 cm threshold (no expected
verdict: statics do not decide it, only the simulation does).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

KINDS_STABLE = ("box_face", "cone_base", "cylinder_upright", "cylinder_side", "plate_flat", "plate_edge_inside")
KINDS_UNSTABLE = ("cone_tip", "box_edge", "plate_edge", "cylinder_rim")
KINDS_HARD = ("box_edge_near", "cone_tip_near", "small_box_edge")


@dataclasses.dataclass(frozen=True)
class Case:
    name: str
    kind: str
    vertices: np.ndarray    # (V, 3) convex shape, canonical frame
    pose: np.ndarray        # (4, 4) rigid, canonical → scene (z up)
    expected_stable: bool | None     # None: statics do not decide it (near the drift threshold)


def box(extents) -> np.ndarray:
    a = 0.5 * np.asarray(extents, np.float64)
    return np.array([[x, y, z] for x in (-a[0], a[0]) for y in (-a[1], a[1]) for z in (-a[2], a[2])])


def prism(radius: float, height: float, sections: int = 16) -> np.ndarray:
    t = 2 * np.pi * np.arange(sections) / sections
    ring = np.stack([radius * np.cos(t), radius * np.sin(t)], 1)
    return np.concatenate([np.c_[ring, np.full(sections, -height / 2)], np.c_[ring, np.full(sections, height / 2)]])


def cone(radius: float, height: float, sections: int = 16) -> np.ndarray:
    """Base at z = −h/4, apex at 3h/4: the centroid of a solid cone at the origin."""
    t = 2 * np.pi * np.arange(sections) / sections
    base = np.stack([radius * np.cos(t), radius * np.sin(t), np.full(sections, -height / 4)], 1)
    return np.concatenate([base, [[0.0, 0.0, 0.75 * height]]])


def _pose(rot: Rotation, rng: np.random.Generator) -> np.ndarray:
    yaw = Rotation.from_euler("z", rng.uniform(0, 2 * np.pi))
    out = np.eye(4)
    out[:3, :3] = (yaw * rot).as_matrix()
    out[:3, 3] = rng.uniform(-0.5, 0.5, 3)
    return out


def make_case(kind: str, rng: np.random.Generator, index: int = 0) -> Case:
    deg = lambda lo, hi: np.radians(rng.uniform(lo, hi)) * rng.choice([-1, 1])  # noqa: E731
    if kind == "box_face":
        verts = box(rng.uniform(0.04, 0.2, 3))
        face = Rotation.from_euler("xy", rng.choice([0, 90, 180, 270], 2), degrees=True)
        rot = Rotation.from_euler("x", deg(0, 3)) * face
    elif kind == "cone_base":
        verts, rot = cone(rng.uniform(0.03, 0.06), rng.uniform(0.06, 0.15)), Rotation.from_euler("x", deg(0, 3))
    elif kind == "cylinder_upright":
        verts = prism(rng.uniform(0.03, 0.06), rng.uniform(0.04, 0.2))
        rot = Rotation.from_euler("x", deg(0, 3))
    elif kind == "cylinder_side":   # lying on a facet (edge-on is a balance point of the 16-gon)
        verts = prism(rng.uniform(0.03, 0.06), rng.uniform(0.06, 0.2))
        rot = Rotation.from_euler("y", 90, degrees=True) * Rotation.from_euler("z", 180 / 16, degrees=True)
    elif kind == "plate_flat":
        verts = box([rng.uniform(0.1, 0.25), rng.uniform(0.1, 0.25), rng.uniform(0.005, 0.015)])
        rot = Rotation.from_euler("x", deg(0, 2))
    elif kind in ("plate_edge", "plate_edge_inside"):
        a, b, c = rng.uniform(0.12, 0.25), rng.uniform(0.12, 0.2), rng.uniform(0.008, 0.015)
        verts = box([a, c, b])                                 # standing: thickness along y, height b
        limit = np.degrees(np.arctan2(c, b))                   # tilt at which the COM leaves the edge face
        tilt = deg(0, 0.3 * limit) if kind == "plate_edge_inside" else deg(limit + 3, limit + 12)
        rot = Rotation.from_euler("x", tilt)
    elif kind == "cone_tip":
        verts = cone(rng.uniform(0.03, 0.06), rng.uniform(0.12, 0.2))
        rot = Rotation.from_euler("x", 180 + np.degrees(deg(2, 10)), degrees=True)
    elif kind == "box_edge":
        b, c = rng.uniform(0.1, 0.2, 2)
        verts = box([rng.uniform(0.05, 0.2), b, c])
        balance = np.arctan2(b, c)                              # the diagonal (b/2, c/2) vertical
        rot = Rotation.from_euler("x", balance + deg(3, 10))
    elif kind == "box_edge_near":
        b, c = rng.uniform(0.1, 0.2, 2)
        verts = box([rng.uniform(0.05, 0.2), b, c])
        rot = Rotation.from_euler("x", np.arctan2(b, c) + deg(0.3, 1.5))
    elif kind == "cone_tip_near":
        verts = cone(rng.uniform(0.03, 0.06), rng.uniform(0.12, 0.2))
        rot = Rotation.from_euler("x", 180 + np.degrees(deg(0.3, 1.5)), degrees=True)
    elif kind == "small_box_edge":
        b, c = rng.uniform(0.03, 0.07, 2)
        verts = box([rng.uniform(0.03, 0.1), b, c])
        rot = Rotation.from_euler("x", np.arctan2(b, c) + deg(3, 10))
    elif kind == "cylinder_rim":
        r, h = rng.uniform(0.02, 0.04), rng.uniform(0.15, 0.25)
        verts = prism(r, h)
        rot = Rotation.from_euler("x", deg(25, 40))
    else:
        raise ValueError(f"unknown case kind {kind!r} (expected one of {KINDS_STABLE + KINDS_UNSTABLE + KINDS_HARD})")
    expected = None if kind == "small_box_edge" else kind in KINDS_STABLE
    return Case(f"{kind}_{index}", kind, verts, _pose(rot, rng), expected)


def case_set(count: int, seed: int = 0, unstable_fraction: float = 0.5) -> list[Case]:
    """``count`` cases cycling through the kinds, about ``unstable_fraction`` of them unstable."""
    rng = np.random.default_rng(seed)
    n_bad = int(round(count * unstable_fraction))
    kinds = [KINDS_UNSTABLE[i % len(KINDS_UNSTABLE)] for i in range(n_bad)]
    kinds += [KINDS_STABLE[i % len(KINDS_STABLE)] for i in range(count - n_bad)]
    return [make_case(kind, rng, i) for i, kind in enumerate(kinds)]


def hard_set(count: int, seed: int = 0) -> list[Case]:
    """``count`` cases near the protocol's edges, cycling through ``KINDS_HARD``."""
    rng = np.random.default_rng(seed)
    return [make_case(KINDS_HARD[i % len(KINDS_HARD)], rng, i) for i in range(count)]
