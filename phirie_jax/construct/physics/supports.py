"""Background collision: the supports the objects stand on, fitted from the scene surface.

In the gravity frame (up = +z): the support heights of the objects (the construction stage's
``support.height``, else an object's lowest point) are grouped within ``HEIGHT_MERGE``. An
infinite plane is the floor: the lowest up-facing surface height holding at least
``FLOOR_MIN_AREA`` when that is below every support, else the lowest support group. Every
support group above the plane becomes a box whose top face is at that height: its footprint is the connected region of
upward-facing surface near that height around the objects on it (2D cells, holes under the
objects closed), boxed by the smallest rotated rectangle. Without a surface, or without
surface near it, the box is the objects' footprint grown by ``FALLBACK_MARGIN``; the geom
records which.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from phirie_jax.construct.physics.ground import PLANE_SIZE
from phirie_jax.geometry import rotation_to_z
from phirie_jax.rotations import compose, matrix_to_quat, yaw_quat

HEIGHT_MERGE = 0.01        # supports closer than this in height are one support, m
UP_FACING_DEG = 20.0       # surface triangles within this of up may be support
BAND = 0.01                # ... and within this of the support height, m
CELL = 0.02                # footprint grid cell, m
FALLBACK_MARGIN = 0.1      # footprint box grown by this without surface evidence, m
FLOOR_MIN_AREA = 0.1       # m² of up-facing surface within one 1 cm height bin to be a floor


@dataclasses.dataclass(frozen=True)
class BackgroundGeom:
    """One support geom of ``scene.xml`` (the manifest's ``physics.background`` rows)."""

    name: str
    type: str                      # "plane" or "box"
    pos: np.ndarray                # (3,) scene frame
    quat: np.ndarray               # (4,) wxyz, scene frame
    size: np.ndarray               # (3,) MuJoCo half sizes (plane: drawn half extent, spacing)
    source: str                    # the evidence it was fitted from, for people

    def record(self) -> dict:
        return {"name": self.name, "type": self.type, "pos": self.pos, "quat": self.quat, "size": self.size,
                "source": self.source}


@dataclasses.dataclass(frozen=True)
class PlacedBody:
    id: int
    points: np.ndarray        # (N, 3) collision vertices placed in the scene frame
    support: float | None     # support height in the gravity frame, when the construction stage found one


def _groups(heights: list[float]) -> list[list[int]]:
    order = np.argsort(heights)
    groups: list[list[int]] = []
    for i in order:
        if groups and heights[i] - heights[groups[-1][-1]] <= HEIGHT_MERGE:
            groups[-1].append(int(i))
        else:
            groups.append([int(i)])
    return groups


def _min_area_rectangle(xy: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Centre (2,), angle (rad) and half extents (2,) of the smallest rotated rectangle."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = xy[ConvexHull(xy).vertices]
    except (QhullError, ValueError):
        hull = xy
    best = None
    for angle in np.radians(np.arange(0.0, 90.0, 1.0)):
        c, s = np.cos(angle), np.sin(angle)
        local = hull @ np.array([[c, -s], [s, c]])
        lo, hi = local.min(0), local.max(0)
        area = float(np.prod(hi - lo))
        if best is None or area < best[0]:
            centre = np.array([[c, -s], [s, c]]) @ (0.5 * (lo + hi))
            best = (area, centre, float(angle), 0.5 * (hi - lo))
    return best[1], best[2], best[3]


@dataclasses.dataclass(frozen=True)
class UpFacing:
    """The scene surface's up-facing triangles (within ``UP_FACING_DEG`` of up) in the gravity
    frame: found once for the whole fit (a splat surface has millions of triangles)."""

    triangles: np.ndarray     # (F, 3, 3) corners, gravity frame
    areas: np.ndarray         # (F,) m²

    @classmethod
    def of(cls, surface, rot: np.ndarray) -> UpFacing:
        """``surface``: a trimesh in the scene frame; ``rot`` (3, 3): scene → gravity."""
        tri = (np.asarray(surface.vertices, np.float64) @ rot.T)[np.asarray(surface.faces)]   # (F, 3, 3)
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        double_area = np.linalg.norm(normal, axis=1)
        up = np.flatnonzero(normal[:, 2] >= np.cos(np.radians(UP_FACING_DEG)) * np.maximum(double_area, 1e-30))
        return cls(tri[up], 0.5 * double_area[up])


def _support_samples(up_facing: UpFacing, height: float) -> np.ndarray:
    """(K, 2) points on the up-facing surface within ``BAND`` of ``height`` (gravity frame), about
    four per cell: big triangles (a scan's tabletop can be two) are sampled, not just their centres."""
    tri, area = up_facing.triangles, up_facing.areas
    near = (tri[:, :, 2].min(1) <= height + BAND) & (tri[:, :, 2].max(1) >= height - BAND)
    faces = np.flatnonzero(near)
    if not len(faces):
        return np.zeros((0, 2))
    counts = np.maximum(1, np.ceil(area[faces] / (0.25 * CELL**2)).astype(int))
    rng = np.random.default_rng(0)
    owner = np.repeat(faces, counts)
    u, v = rng.random((2, len(owner)))
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    t = tri[owner]
    points = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
    return points[np.abs(points[:, 2] - height) <= BAND, :2]


def _surface_footprint(up_facing: UpFacing, height: float, seeds: np.ndarray) -> np.ndarray | None:
    """(K, 2) cell centres of the up-facing surface region near ``height`` around the seeds."""
    from scipy import ndimage

    xy = _support_samples(up_facing, height)
    if len(xy) < 3:
        return None
    lo = np.minimum(xy.min(0), seeds.min(0)) - 2 * CELL
    shape = np.ceil((np.maximum(xy.max(0), seeds.max(0)) + 2 * CELL - lo) / CELL).astype(int) + 1
    grid = np.zeros(shape, bool)
    ij = np.floor((xy - lo) / CELL).astype(int)
    grid[ij[:, 0], ij[:, 1]] = True
    grid = ndimage.binary_closing(grid, iterations=2, border_value=0) | grid
    grid = ndimage.binary_fill_holes(grid)
    labels, _ = ndimage.label(grid, structure=np.ones((3, 3)))
    seed_ij = np.clip(np.floor((seeds - lo) / CELL).astype(int), 0, shape - 1)
    wanted = {int(labels[i, j]) for i, j in seed_ij} - {0}
    if not wanted:
        return None
    cells = np.argwhere(np.isin(labels, list(wanted)))
    return lo + (cells + 0.5) * CELL


def _surface_floor(up_facing: UpFacing) -> float | None:
    """Lowest height of up-facing surface with at least ``FLOOR_MIN_AREA`` in one 1 cm bin."""
    if not len(up_facing.areas):
        return None
    z = up_facing.triangles[:, :, 2].mean(1)                     # the triangles' centres' heights
    area = up_facing.areas
    edges = np.arange(z.min(), z.max() + 0.02, 0.01)
    counts, edges = np.histogram(z, bins=edges, weights=area)
    big = np.flatnonzero(counts >= FLOOR_MIN_AREA)
    if not len(big):
        return None
    in_bin = (z >= edges[big[0]]) & (z <= edges[big[0] + 1])
    return float(np.average(z[in_bin], weights=area[in_bin]))


def fit_background(bodies: list[PlacedBody], up, surface=None, thickness: float = 0.04,
                   mode: str = "supports") -> list[BackgroundGeom]:
    """Support geoms (scene frame) under ``bodies``; ``surface`` is a trimesh of the scene or None."""
    rot = rotation_to_z(up)                      # scene → gravity
    to_scene = matrix_to_quat(rot.T)             # gravity → scene, wxyz
    if not bodies:
        return [BackgroundGeom("floor", "plane", np.zeros(3), to_scene,
                               np.array(PLANE_SIZE), "no objects: plane at 0")]
    grav = [b.points @ rot.T for b in bodies]
    heights = [b.support if b.support is not None else float(g[:, 2].min()) for b, g in zip(bodies, grav)]
    groups = _groups(heights)
    up_facing = UpFacing.of(surface, rot) if (surface is not None and mode == "supports") else None
    floor = _surface_floor(up_facing) if up_facing is not None else None
    if floor is not None and floor < min(heights) - HEIGHT_MERGE:
        source = "scene surface (lowest up-facing region)"
    else:
        floor = float(np.median([heights[i] for i in groups[0]]))
        source = "lowest support (objects " + ", ".join(str(bodies[i].id) for i in groups[0]) + ")"
        groups = groups[1:]
    geoms = [BackgroundGeom("floor", "plane", rot.T @ np.array([0.0, 0.0, floor]),
                            to_scene,
                            np.array(PLANE_SIZE), source)]
    if mode == "plane":
        return geoms
    for k, group in enumerate(groups):
        height = float(np.median([heights[i] for i in group]))
        seeds = np.concatenate([grav[i][:, :2] for i in group])
        footprint = _surface_footprint(up_facing, height, seeds) if up_facing is not None else None
        if footprint is not None and len(footprint) >= 3:
            xy, source = np.concatenate([footprint, seeds]), "scene surface"
            margin = 0.5 * CELL
        else:
            xy, source, margin = seeds, "objects' footprint (no surface evidence)", FALLBACK_MARGIN
        centre, angle, half = _min_area_rectangle(xy)
        half = half + margin
        pos_g = np.array([centre[0], centre[1], height - 0.5 * thickness])
        quat = compose(to_scene, yaw_quat(angle))
        ids = ", ".join(str(bodies[i].id) for i in group)
        geoms.append(BackgroundGeom(f"support_{k}", "box", rot.T @ pos_g, quat,
                                    np.array([half[0], half[1], 0.5 * thickness]), f"{source} (objects {ids})"))
    return geoms
