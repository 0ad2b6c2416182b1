"""Procedural household objects and furniture with surface colour, in metres.

Every object mesh is watertight and canonical: z up, resting on z = 0, centred on
the z axis. Revolved objects (mug, bowl, bottle, can) come from closed 2D profiles,
so they have real wall thickness; colours are functions of the canonical position,
so a texture moves with the object.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

ColourFn = Callable[[np.ndarray], np.ndarray]  # (P, 3) canonical points → (P, 3) rgb in [0, 1]
REVOLVE_SECTIONS = 48
CATEGORIES = ("mug", "bowl", "box", "bottle", "can", "fruit")


@dataclasses.dataclass(frozen=True)
class ObjectShape:
    category: str
    mesh: "object"           # trimesh.Trimesh, canonical frame
    colour: ColourFn
    shininess: float         # amplitude of the view-dependent SH lobe


def _hash_noise(points: np.ndarray, frequency: float, seed: int) -> np.ndarray:
    """Smooth-ish deterministic noise in [-1, 1]: a sum of random plane waves."""
    rng = np.random.default_rng(seed)
    dirs = rng.normal(size=(6, 3))
    phases = rng.uniform(0, 2 * np.pi, 6)
    return np.mean(np.sin(frequency * points @ dirs.T + phases), axis=1) * np.sqrt(2)


def _mix(a, b, t):
    t = np.clip(t, 0.0, 1.0)[:, None]
    return (1 - t) * np.asarray(a) + t * np.asarray(b)


def _revolve(profile: list[tuple[float, float]]):
    """Watertight solid of revolution of a closed (radius, height) profile about z."""
    import trimesh

    mesh = trimesh.creation.revolve(np.asarray(profile, float), sections=REVOLVE_SECTIONS)
    mesh.merge_vertices()
    mesh.fix_normals()
    return mesh


def _half_ring(major: float, minor: float, sections=(24, 12)):
    """Closed half torus in the xz-plane bulging towards +x (a mug handle), centred at the origin."""
    import trimesh

    nu, nv = sections
    u = np.linspace(-np.pi / 2, np.pi / 2, nu + 1)
    v = np.linspace(0, 2 * np.pi, nv, endpoint=False)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    radial = major + minor * np.cos(vv)
    verts = np.stack([radial * np.cos(uu), minor * np.sin(vv), radial * np.sin(uu)], -1).reshape(-1, 3)
    faces = []
    for i in range(nu):
        for j in range(nv):
            a, b = i * nv + j, i * nv + (j + 1) % nv
            c, d = a + nv, b + nv
            faces += [[a, c, b], [b, c, d]]
    centres = np.array([[0, 0, -major], [0, 0, major]], float)
    cap0, cap1 = len(verts), len(verts) + 1
    for j in range(nv):
        faces.append([cap0, j, (j + 1) % nv])
        faces.append([cap1, nu * nv + (j + 1) % nv, nu * nv + j])
    mesh = trimesh.Trimesh(np.vstack([verts, centres]), np.array(faces), process=True)
    mesh.fix_normals()
    return mesh


def _base_colour(rng) -> np.ndarray:
    """A saturated, well-lit colour (distinct from the grey/brown furniture)."""
    import colorsys

    return np.array(colorsys.hsv_to_rgb(rng.uniform(), rng.uniform(0.55, 0.9), rng.uniform(0.6, 0.95)))


def mug(rng, seed: int) -> ObjectShape:
    import trimesh

    r, h, wall, floor = rng.uniform(0.036, 0.045), rng.uniform(0.085, 0.105), 0.005, 0.008
    body = _revolve([(0, 0), (r, 0), (r, h), (r - wall, h), (r - wall, floor), (0, floor)])
    handle = _half_ring(major=0.028, minor=0.006)
    handle.apply_translation([r - 0.004, 0, h * 0.5])
    mesh = trimesh.util.concatenate([body, handle])
    base, band = _base_colour(rng), _base_colour(rng)

    def colour(p):
        stripe = (np.abs(p[:, 2] - 0.6 * h) < 0.012).astype(float)
        return _mix(base, band, stripe)

    return ObjectShape("mug", mesh, colour, shininess=0.08)


def bowl(rng, seed: int) -> ObjectShape:
    r, h, wall = rng.uniform(0.065, 0.085), rng.uniform(0.05, 0.065), 0.006
    foot = 0.55 * r
    ts = np.linspace(0, np.pi / 2, 10)
    outer = [(foot + (r - foot) * np.sin(t), h * (1 - np.cos(t))) for t in ts]
    inner = [(max(foot - wall, 0) + (r - wall - foot + wall) * np.sin(t), wall + (h - wall) * (1 - np.cos(t)))
             for t in ts[::-1]]
    mesh = _revolve([(0, 0), *outer, *inner, (0, wall)])
    base, rim = _base_colour(rng), _base_colour(rng)

    def colour(p):
        radius = np.linalg.norm(p[:, :2], axis=1)
        return _mix(base, rim, (radius / r - 0.8) * 5)

    return ObjectShape("bowl", mesh, colour, shininess=0.06)


def box(rng, seed: int) -> ObjectShape:
    import trimesh

    ext = np.array([rng.uniform(0.12, 0.18), rng.uniform(0.05, 0.08), rng.uniform(0.14, 0.22)])
    mesh = trimesh.creation.box(extents=ext)
    mesh.apply_translation([0, 0, ext[2] / 2])
    base, print_colour = _base_colour(rng), _base_colour(rng)

    def colour(p):  # a printed carton: blocks of colour and a light panel
        checker = (np.floor(p[:, 0] / 0.03) + np.floor(p[:, 2] / 0.03)) % 2
        panel = (np.abs(p[:, 2] - ext[2] * 0.55) < ext[2] * 0.18).astype(float)
        out = _mix(base, print_colour, 0.35 * checker)
        return _mix(out, [0.92, 0.9, 0.85], panel)

    return ObjectShape("box", mesh, colour, shininess=0.03)


def bottle(rng, seed: int) -> ObjectShape:
    r, h = rng.uniform(0.03, 0.038), rng.uniform(0.19, 0.24)
    neck, cap = 0.012, 0.014
    mesh = _revolve([(0, 0), (r, 0), (r, 0.62 * h), (neck, 0.85 * h), (neck, 0.9 * h),
                     (cap, 0.9 * h), (cap, h), (0, h)])
    base, label = _base_colour(rng), _base_colour(rng)

    def colour(p):
        band = ((p[:, 2] > 0.2 * h) & (p[:, 2] < 0.5 * h)).astype(float)
        capped = (p[:, 2] > 0.895 * h).astype(float)
        return _mix(_mix(base, label, band), [0.95, 0.95, 0.95], capped)

    return ObjectShape("bottle", mesh, colour, shininess=0.1)


def can(rng, seed: int) -> ObjectShape:
    r, h = rng.uniform(0.03, 0.036), rng.uniform(0.09, 0.12)
    mesh = _revolve([(0, 0), (r, 0), (r, h), (0, h)])
    label, stripe = _base_colour(rng), _base_colour(rng)

    def colour(p):
        side = np.linalg.norm(p[:, :2], axis=1) > r * 0.98
        label_zone = side & (p[:, 2] > 0.012) & (p[:, 2] < h - 0.012)
        angle = np.arctan2(p[:, 1], p[:, 0])
        stripes = (np.sin(6 * angle) > 0.6).astype(float)
        out = _mix(label, stripe, stripes)
        return np.where(label_zone[:, None], out, np.array([0.75, 0.75, 0.78]))

    return ObjectShape("can", mesh, colour, shininess=0.12)


def fruit(rng, seed: int) -> ObjectShape:
    import trimesh

    r = rng.uniform(0.035, 0.045)
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    v = mesh.vertices
    bumps = 1.0 + 0.08 * _hash_noise(v, 2.5, seed)
    v = v * bumps[:, None] * np.array([r, r, 0.9 * r])
    v[:, 2] = np.maximum(v[:, 2], -0.8 * r)  # a flattened spot to rest on
    v[:, 2] -= v[:, 2].min()
    mesh = trimesh.Trimesh(v, mesh.faces, process=True)
    mesh.fix_normals()
    base = np.array([rng.uniform(0.7, 0.95), rng.uniform(0.1, 0.5), 0.08])

    def colour(p):
        speckle = _hash_noise(p, 180.0, seed + 1)
        return np.clip(base * (1.0 + 0.15 * speckle[:, None]), 0, 1)

    return ObjectShape("fruit", mesh, colour, shininess=0.07)


MAKERS = {"mug": mug, "bowl": bowl, "box": box, "bottle": bottle, "can": can, "fruit": fruit}


def make_object(category: str, rng: np.random.Generator, seed: int) -> ObjectShape:
    return MAKERS[category](rng, seed)


@dataclasses.dataclass(frozen=True)
class Furniture:
    """Floor and table in world coordinates (z up, floor at z = 0)."""

    floor: "object"
    table: "object"           # top slab and four legs
    table_top_z: float        # height of the tabletop surface
    top_extent: np.ndarray    # (2,) tabletop size in x, y, centred at the origin


def make_furniture(floor_size: float = 3.0, top=(1.2, 0.8), height=0.75, thickness=0.04) -> Furniture:
    import trimesh

    floor = trimesh.creation.box(extents=[floor_size, floor_size, 0.02])
    floor.apply_translation([0, 0, -0.01])
    slab = trimesh.creation.box(extents=[top[0], top[1], thickness])
    slab.apply_translation([0, 0, height - thickness / 2])
    legs = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            leg = trimesh.creation.box(extents=[0.05, 0.05, height - thickness])
            leg.apply_translation([sx * (top[0] / 2 - 0.06), sy * (top[1] / 2 - 0.06),
                                   (height - thickness) / 2])
            legs.append(leg)
    return Furniture(floor, trimesh.util.concatenate([slab, *legs]), height, np.asarray(top, float))


def floor_colour(p: np.ndarray) -> np.ndarray:
    """Large grey tiles with grout lines."""
    tile = ((np.floor(p[:, 0] / 0.5) + np.floor(p[:, 1] / 0.5)) % 2)[:, None]
    grout = ((np.abs((p[:, 0] + 0.25) % 0.5 - 0.25) < 0.006) | (np.abs((p[:, 1] + 0.25) % 0.5 - 0.25) < 0.006))
    out = 0.42 + 0.08 * tile + 0.02 * _hash_noise(p, 40.0, 3)[:, None]
    out = np.repeat(out, 3, axis=1) * np.array([1.0, 0.98, 0.95])
    return np.where(grout[:, None], 0.25, out)


def table_colour(p: np.ndarray) -> np.ndarray:
    """Wood: grain along x, warm brown."""
    grain = np.sin(p[:, 1] * 180.0 + 3.0 * _hash_noise(p * np.array([0.2, 1.0, 1.0]), 8.0, 5))
    return np.clip(np.array([0.55, 0.37, 0.22]) * (1.0 + 0.12 * grain[:, None]), 0, 1)
