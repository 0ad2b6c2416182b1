"""Support plane and the fill grid of one removed object (host side; the fit is ``kernels.fill``).

Names in ``code`` are fields of ``PlaneConfig`` (the plane) and ``FillConfig`` (the fill).

1. Ring: kept Gaussian centres (opaque enough) whose horizontal distance from the object's
   footprint (Q_i and the placed asset, rasterized on a ``grid`` raster in the gravity frame)
   is within [``ring_inner``, ``ring_outer``] and whose height is within ``ring_height`` of
   the object's base.
2. Plane: RANSAC over the ring (``ransac_iterations`` seeded hypotheses, inliers within
   ``threshold``, normal within ``max_tilt_deg`` of up, passing within ``base_tolerance`` of
   the object's base), then least-squares refits on the inliers. Too few ring points or
   inliers, or no plane near up: an *unsupported region*.
3. Cells of a ``grid`` lattice on the plane. A cell is *covered* when a kept Gaussian of the
   plane's slab lies within ``cover_factor`` × their median spacing. A cell is *supported* when
   it lies inside the closure of what is known to be plane there: covered cells, the object's
   contact base (observed points, and asset points when the shape passed its registration check,
   within ``slab`` of the plane) and removed Gaussians of the slab
   (the plane was captured there). Exposed = supported, not covered and under the object's
   shadow (its points and removed Gaussians projected on the plane). The fill covers the
   exposed cells grown by ``margin``; past a table's edge nothing is supported, so nothing is
   laid in the air.
4. Disks: one flat Gaussian per fill cell, normal-aligned, σ = ``disk_sigma`` × grid in plane.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import ndimage

from kernels.sh import rgb_to_sh_dc
from phirie_jax.construct.background.config import BackgroundConfig
from phirie_jax.geometry import logit, rotation_to_z
from phirie_jax.types import GaussianSplatData

REFITS = 3            # least-squares refits of the RANSAC plane on its inliers
DEGENERATE = 1e-12    # |n|² of a hypothesis from collinear samples
ASSET_SAMPLE_CELLS = 4  # asset surface samples per grid cell area (its shadow has no gaps)


def tangent_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (u, v) with (u, v, normal) right-handed."""
    helper = np.array([1.0, 0, 0]) if abs(normal[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(helper, normal)
    u /= np.linalg.norm(u)
    return u, np.cross(normal, u)


@dataclasses.dataclass(frozen=True)
class Plane:
    point: np.ndarray   # (3,) on the plane
    normal: np.ndarray  # (3,) unit, towards up
    inliers: int
    points: int
    rms: float          # metres, of the inliers

    def height(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, np.float64) - self.point) @ self.normal

    def as_dict(self) -> dict:
        return {"point": self.point.round(6).tolist(), "normal": self.normal.round(6).tolist(),
                "inliers": self.inliers, "points": self.points, "rms_m": round(self.rms, 6)}


def fit_plane(points: np.ndarray, up: np.ndarray, config: BackgroundConfig, anchor: np.ndarray | None = None
              ) -> tuple[Plane | None, str | None]:
    """Robust plane of ``points`` (P, 3): RANSAC then least-squares refits. (None, reason) if none.

    anchor: the object's base point; a support plane passes within ``PlaneConfig.base_tolerance`` of it
    (a table's underside, parallel and a few cm below, often has more points in the ring).
    """
    n_pts = len(points)
    if n_pts < max(3, config.plane.min_points):
        return None, f"{n_pts} surface points around the footprint (need {config.plane.min_points})"
    rng = np.random.default_rng(config.seed)
    samples = np.stack([rng.choice(n_pts, 3, replace=False) for _ in range(config.plane.ransac_iterations)])
    a, b, c = points[samples[:, 0]], points[samples[:, 1]], points[samples[:, 2]]
    normals = np.cross(b - a, c - a)
    norm2 = np.sum(normals**2, axis=1)
    normals = normals / np.sqrt(np.maximum(norm2, DEGENERATE))[:, None]
    cos_tilt = np.abs(normals @ up)
    ok = (norm2 > DEGENERATE) & (cos_tilt >= np.cos(np.deg2rad(config.plane.max_tilt_deg)))
    if anchor is not None:
        ok &= np.abs(np.sum((anchor - a) * normals, axis=1)) <= config.plane.base_tolerance
    dist = np.abs((points[None] - a[:, None]) @ normals[..., None])[..., 0]  # (H, P)
    counts = np.where(ok, np.sum(dist <= config.plane.threshold, axis=1), -1)
    best = int(np.argmax(counts))
    if counts[best] < 3:
        where = "" if anchor is None else f" passing within {config.plane.base_tolerance} m of the object's base"
        return None, f"no plane within {config.plane.max_tilt_deg}° of up{where} among {n_pts} surface points"
    inliers = dist[best] <= config.plane.threshold
    centre, normal = a[best], normals[best]
    for _ in range(REFITS):
        centre = points[inliers].mean(0)
        _, _, vt = np.linalg.svd(points[inliers] - centre, full_matrices=False)
        normal = vt[-1]
        new = np.abs((points - centre) @ normal) <= config.plane.threshold
        if new.sum() < 3:
            break
        inliers = new
    if normal @ up < 0:
        normal = -normal
    if normal @ up < np.cos(np.deg2rad(config.plane.max_tilt_deg)):
        return None, f"the best plane is tilted {np.degrees(np.arccos(normal @ up)):.0f}° from up"
    if anchor is not None and abs((anchor - centre) @ normal) > config.plane.base_tolerance:
        return None, "the refitted plane does not pass by the object's base"
    fraction = inliers.mean()
    rms = float(np.sqrt(np.mean(((points[inliers] - centre) @ normal) ** 2)))
    plane = Plane(centre, normal, int(inliers.sum()), n_pts, rms)
    if fraction < config.plane.min_inlier_fraction:
        return None, (f"{fraction:.0%} of the surface points around the footprint are on one plane "
                      f"(need {config.plane.min_inlier_fraction:.0%})")
    return plane, None


BOX_SLACK = 1e-9  # metres around a prefilter box: its test never decides a point on its boundary


def within_box(points: np.ndarray, lo: np.ndarray, hi: np.ndarray, index: BoxIndex | None = None) -> np.ndarray:
    """Indices of the (N, 3) ``points`` inside the box [lo, hi] grown by ``BOX_SLACK``: a cheap
    prefilter whose survivors then take the exact test (the box holds every point that can pass it).
    index: ``BoxIndex(points)``, when many boxes are asked of the same points."""
    lo, hi = np.asarray(lo) - BOX_SLACK, np.asarray(hi) + BOX_SLACK
    if index is not None:
        return index.within(lo, hi)
    return np.flatnonzero(np.all((points >= lo) & (points <= hi), axis=1))


class BoxIndex:
    """Points (N, 3) sorted along x once, so that each box of many (one per object) tests only the
    points of its x-slab instead of all N: ``within(lo, hi)`` is the sorted indices of the points in
    the closed box, the same as testing every point."""

    def __init__(self, points: np.ndarray):
        self.points = points
        self.order = np.argsort(points[:, 0], kind="stable")
        self.xs = points[self.order, 0]

    def within(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        start, stop = np.searchsorted(self.xs, lo[0], "left"), np.searchsorted(self.xs, hi[0], "right")
        slab = self.order[start:stop]
        pts = self.points[slab]
        return np.sort(slab[np.all((pts >= lo) & (pts <= hi), axis=1)])


def _raster(xy: np.ndarray, origin: np.ndarray, cell: float, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool grid with the cells that contain any of the points (outside points dropped)."""
    grid = np.zeros(shape, bool)
    ij = np.floor((xy - origin) / cell).astype(np.int64)
    ok = (ij[:, 0] >= 0) & (ij[:, 0] < shape[0]) & (ij[:, 1] >= 0) & (ij[:, 1] < shape[1])
    grid[ij[ok, 0], ij[ok, 1]] = True
    return grid


def object_points(q: np.ndarray, mesh: tuple[np.ndarray, np.ndarray] | None, grid: float, seed: int) -> np.ndarray:
    """Q_i and (when registered) points on the placed asset's surface dense enough to leave no gaps
    in its shadow on a ``grid`` raster."""
    if mesh is None:
        return q
    import trimesh

    surface = trimesh.Trimesh(mesh[0], mesh[1], process=False)
    count = int(min(200_000, max(1000, ASSET_SAMPLE_CELLS * surface.area / grid**2)))
    samples, _ = trimesh.sample.sample_surface(surface, count, seed=seed)
    return np.concatenate([q, mesh[0], np.asarray(samples)])


def ring_points(kept_means: np.ndarray, kept_opacity: np.ndarray, obj_points: np.ndarray, up: np.ndarray,
                base: float, config: BackgroundConfig, index: BoxIndex | None = None) -> np.ndarray:
    """Indices of kept Gaussians in the ring around the footprint (module docstring, 1).

    kept_means (K, 3), kept_opacity (K,), obj_points (P, 3), up (3,) unit, base: the object's base
    height along up; index: ``BoxIndex(kept_means)``, shared by the objects."""

    rot = rotation_to_z(up)
    obj_g = obj_points @ rot.T
    cell = config.fill.grid
    origin = obj_g[:, :2].min(0) - config.plane.ring_outer - cell
    shape = tuple(np.ceil((obj_g[:, :2].max(0) + config.plane.ring_outer + cell - origin) / cell).astype(int) + 1)
    footprint = _raster(obj_g[:, :2], origin, cell, shape)
    dist = ndimage.distance_transform_edt(~footprint) * cell
    # only the Gaussians of a world box holding the raster's column around the base can be in the ring
    corners = np.stack(np.meshgrid(*[[a, b] for a, b in zip(
        [*origin, base - config.plane.ring_height], [*(origin + np.array(shape) * cell), base + config.plane.ring_height])],
        indexing="ij"), -1).reshape(-1, 3) @ rot
    nearby = within_box(kept_means, corners.min(0), corners.max(0), index)
    kept_means, kept_opacity = kept_means[nearby], kept_opacity[nearby]
    kept_g = kept_means @ rot.T
    ij = np.floor((kept_g[:, :2] - origin) / cell).astype(np.int64)
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < shape[0]) & (ij[:, 1] >= 0) & (ij[:, 1] < shape[1])
    d = np.full(len(kept_means), np.inf)
    d[inside] = dist[ij[inside, 0], ij[inside, 1]]
    near_base = np.abs(kept_g[:, 2] - base) <= config.plane.ring_height
    return nearby[(d >= config.plane.ring_inner) & (d <= config.plane.ring_outer) & near_base
                  & (kept_opacity >= config.plane.min_opacity)]


@dataclasses.dataclass(frozen=True)
class FillRegion:
    """The fill of one object on its plane."""

    plane: Plane
    u: np.ndarray            # (3,) in-plane axes
    v: np.ndarray
    centres: np.ndarray      # (K, 3) disk centres (cells of the fill)
    exposed: int             # exposed cells (before the margin)
    covered_spacing: float   # median spacing of the kept plane Gaussians, metres

    @property
    def num(self) -> int:
        return len(self.centres)

    def subset(self, keep: np.ndarray) -> FillRegion:
        """The fill without the cells where ``keep`` (K,) bool is False (``exposed`` as it was)."""
        return dataclasses.replace(self, centres=self.centres[keep])

    def quats(self) -> np.ndarray:
        """(K, 4) wxyz rotation with columns (u, v, normal)."""
        from phirie_jax.rotations import matrix_to_quat

        frame = np.stack([self.u, self.v, self.plane.normal], axis=-1)
        q = matrix_to_quat(frame)
        return np.tile(q, (self.num, 1))


def fill_region(plane: Plane, kept_means: np.ndarray, kept_opacity: np.ndarray, obj_points: np.ndarray,
                removed_means: np.ndarray, config: BackgroundConfig, index: BoxIndex | None = None,
                contact_points: np.ndarray | None = None) -> FillRegion:
    """The exposed cells of the plane under one object, grown by the margin (module docstring, 3).

    kept_means (K, 3), kept_opacity (K,), obj_points (P, 3) its shadow, removed_means (R, 3) the
    object's R_i; index: ``BoxIndex(kept_means)``, shared by the objects; contact_points (C, 3):
    the points whose base is evidence of the plane (default ``obj_points``; the stage gives Q_i: an
    asset's base is a guess, and past a support's edge it would lay the fill in the air).
    """
    from scipy.spatial import cKDTree

    u, v = tangent_basis(plane.normal)
    cell = config.fill.grid

    def plane_xy(x):
        d = np.asarray(x, np.float64) - plane.point
        return np.stack([d @ u, d @ v], axis=1)

    h_obj = plane.height(obj_points)
    shadow_pts = np.concatenate([plane_xy(obj_points[h_obj > -config.fill.slab]),
                                 plane_xy(removed_means[plane.height(removed_means) > -config.fill.slab])])
    reach = config.removal.obs_radius + config.fill.margin + 2 * cell
    origin = shadow_pts.min(0) - reach
    shape = tuple(np.ceil((shadow_pts.max(0) + reach - origin) / cell).astype(int) + 1)
    ia, ib = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    centres_xy = origin + (np.stack([ia, ib], -1) + 0.5) * cell  # (H, W, 2)

    lo, hi = origin - reach, origin + np.array(shape) * cell + reach
    # only the kept Gaussians of a world box holding the local slab (in-plane [lo, hi], ±slab) matter
    corners = np.stack(np.meshgrid([lo[0], hi[0]], [lo[1], hi[1]], [-config.fill.slab, config.fill.slab],
                                   indexing="ij"), -1).reshape(-1, 3)
    corners = plane.point + corners[:, :1] * u + corners[:, 1:2] * v + corners[:, 2:] * plane.normal
    nearby = within_box(kept_means, corners.min(0), corners.max(0), index)
    kept_means, kept_opacity = kept_means[nearby], kept_opacity[nearby]
    h_kept = plane.height(kept_means)
    on_plane = (np.abs(h_kept) <= config.fill.slab) & (kept_opacity >= config.plane.min_opacity)
    kept_xy = plane_xy(kept_means[on_plane])
    local = kept_xy[np.all((kept_xy >= lo) & (kept_xy <= hi), axis=1)]
    if len(local) >= 2:
        d_nn, _ = cKDTree(local).query(local, k=2)
        spacing = float(np.median(d_nn[:, 1]))
        d, _ = cKDTree(local).query(centres_xy.reshape(-1, 2), distance_upper_bound=max(cell, config.fill.cover_factor * spacing))
        covered = np.isfinite(d).reshape(shape)
    else:
        spacing, covered = float("nan"), np.zeros(shape, bool)

    removed_slab = removed_means[np.abs(plane.height(removed_means)) <= config.fill.slab]
    contact = obj_points if contact_points is None else contact_points
    h_contact = plane.height(contact)
    base = contact[(h_contact > -config.fill.slab) & (h_contact <= config.fill.slab)]
    known = covered | _raster(plane_xy(removed_slab), origin, cell, shape) | _raster(plane_xy(base), origin, cell, shape)
    supported = ndimage.binary_fill_holes(ndimage.binary_closing(known, iterations=2, border_value=0))
    shadow = ndimage.binary_fill_holes(ndimage.binary_closing(_raster(shadow_pts, origin, cell, shape), iterations=2))
    exposed = supported & ~covered & shadow
    grow = round(config.fill.margin / cell)
    fill = ndimage.binary_dilation(exposed, iterations=grow) & supported if grow > 0 else exposed
    xy = centres_xy[fill]
    centres = plane.point + xy[:, :1] * u + xy[:, 1:] * v
    return FillRegion(plane, u, v, centres, int(exposed.sum()), spacing)


NEIGHBOUR_REACH = 0.05  # metres: the colour neighbours are first sought within this box around the centres


def neighbour_colours(centres: np.ndarray, kept_means: np.ndarray, kept_rgb: np.ndarray, k: int) -> np.ndarray:
    """(K, 3) mean colour of the k nearest kept Gaussians (``kept_rgb`` (N, 3)) of each centre.

    Sought among the Gaussians of the centres' box grown by ``NEIGHBOUR_REACH`` first (a tree of
    the whole tabletop per object was most of this step): when every centre's k-th neighbour there
    lies within that reach, no Gaussian outside the box can be nearer, and these are the k nearest
    of all; otherwise all are searched."""
    from scipy.spatial import cKDTree

    if len(kept_means) == 0:
        return np.full((len(centres), 3), 0.5)
    k = min(k, len(kept_means))
    if len(centres):
        local = within_box(kept_means, centres.min(0) - NEIGHBOUR_REACH, centres.max(0) + NEIGHBOUR_REACH)
        if len(local) >= k:
            d, nn = cKDTree(kept_means[local]).query(centres, k=k)
            if np.all(d.reshape(len(centres), -1)[:, -1] <= NEIGHBOUR_REACH):
                return kept_rgb[local[nn.reshape(len(centres), -1)]].mean(axis=1)
    _, nn = cKDTree(kept_means).query(centres, k=k)
    return kept_rgb[nn.reshape(len(centres), -1)].mean(axis=1)


def disks(region: FillRegion, rgb: np.ndarray, config: BackgroundConfig, sh_coeffs: int) -> GaussianSplatData:
    """The initial disks of a fill region, coloured ``rgb`` (K, 3), SH padded to ``sh_coeffs``."""
    sigma = config.fill.disk_sigma * config.fill.grid
    n = region.num
    sh = np.zeros((n, sh_coeffs, 3), np.float32)
    sh[:, 0] = rgb_to_sh_dc(np.asarray(rgb, np.float64))
    return GaussianSplatData(
        means=region.centres.astype(np.float32), quats=region.quats().astype(np.float32),
        log_scales=np.tile(np.log([sigma, sigma, config.fill.disk_thickness * sigma]), (n, 1)).astype(np.float32),
        opacity_logits=np.full(n, logit(config.fill.init_opacity), np.float32), sh=sh)
