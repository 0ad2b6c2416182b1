"""Automatic instance discovery with no learned weights (``--masks auto``).

1. Sample the observed surface: first hits of pixel rays of every camera (on a stride),
   thinned to one per ``sample_voxel``, with normals turned towards the camera.
2. Supports under the scene's up (+z of the frame resolved before observation, never
   re-derived here): peaks of the height histogram of upward-facing samples, each refitted by least squares on its
   inliers and kept when it covers ``min_support_area``. Each support gets a 2D footprint
   (occupancy of its inliers, holes closed — the table under an object is never seen).
3. What stands on a support: samples above it (by more than the plane threshold, at most
   ``max_object_height``) inside its footprint, assigned to the nearest support below.
   Euclidean clustering (radius graph, ``cluster_eps``) per support; a cluster is an
   object when it is big enough, small enough and its lowest point is near the support.
   The object's sides within the plane threshold of the support (not upward-facing,
   next to the cluster) are given back to it.
4. Per-view masks: each pixel's first hit on the surface takes the label of the nearest
   sample (within two sample voxels): projection of each cluster with occlusion.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from phirie_jax.observe.config import AutoMaskConfig
from phirie_jax.observe.masks import Segment, ViewFailure, ViewMasks, camera_problem
from phirie_jax.observe.raycast import Raycaster
from phirie_jax.observe.surface import pack_keys
from phirie_jax.types import Camera


@dataclasses.dataclass(frozen=True)
class Support:
    normal: np.ndarray     # (3,) unit, pointing up
    offset: float          # plane: normal · x = offset
    inliers: int           # samples on it
    area: float            # m², samples × sample_voxel²
    origin: np.ndarray     # (2,) footprint grid origin in plane coordinates
    footprint: np.ndarray  # (U, V) bool occupancy, holes filled
    basis: np.ndarray      # (2, 3) in-plane axes

    def height(self, points):
        return points @ self.normal - self.offset

    def covers(self, points, cell: float) -> np.ndarray:
        uv = np.floor((points @ self.basis.T - self.origin) / cell).astype(np.int64)
        ok = (uv >= 0).all(1) & (uv[:, 0] < self.footprint.shape[0]) & (uv[:, 1] < self.footprint.shape[1])
        out = np.zeros(len(points), bool)
        out[ok] = self.footprint[uv[ok, 0], uv[ok, 1]]
        return out

    def as_dict(self) -> dict:
        return {"normal": self.normal.round(6).tolist(), "offset": round(float(self.offset), 6),
                "inliers": self.inliers, "area_m2": round(self.area, 4)}


@dataclasses.dataclass(frozen=True)
class AutoSegmentation:
    points: np.ndarray      # (N, 3) observed surface samples
    labels: np.ndarray      # (N,) int64 object id per sample, 0 = support or nothing
    supports: list[Support]
    objects: list[dict]     # accepted clusters: id, support, points, extent, base gap
    rejected: list[dict]    # clusters left out, with the reason
    up: np.ndarray          # (3,)


def observed_samples(raycaster: Raycaster, cameras: list[Camera], stride: int, voxel: float):
    """Surface samples (N, 3) the cameras see, one per voxel, and normals (N, 3) facing a camera."""
    points, normals = [], []
    for cam in cameras:
        hits, _, _ = raycaster.cast_camera(cam, stride)
        points.append(hits.points[hits.hit])
        normals.append(hits.normal[hits.hit])
    points, normals = np.concatenate(points), np.concatenate(normals)
    _, first = np.unique(pack_keys(np.floor(points / voxel)), return_index=True)
    first = np.sort(first)
    return points[first], normals[first]


def _plane_fit(points: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, float]:
    centre = points.mean(0)
    normal = np.linalg.svd(points - centre, full_matrices=False)[2][-1]
    normal = normal if normal @ up >= 0 else -normal
    return normal, float(normal @ centre)


def find_supports(points: np.ndarray, normals: np.ndarray, up: np.ndarray, config: AutoMaskConfig,
                  sample_voxel: float) -> list[Support]:
    """Upward-facing support planes (largest first) under the scene's ``up`` (3,)."""
    cos_tilt = np.cos(np.deg2rad(config.up_max_tilt_deg))
    facing = normals @ up > cos_tilt
    if facing.sum() < 3:
        return []
    cand = points[facing]
    heights = cand @ up
    thr = config.plane_threshold
    edges = np.arange(heights.min() - thr, heights.max() + 2 * thr, thr)
    counts, _ = np.histogram(heights, edges)
    supports, used = [], np.zeros(len(cand), bool)
    min_count = config.min_support_area / sample_voxel**2
    while True:
        peak = int(np.argmax(counts))
        if counts[peak] < min_count / 3:  # a peak bin holds ≥ 1/3 of a support's inliers
            break
        centre = 0.5 * (edges[peak] + edges[peak + 1])
        near = ~used & (np.abs(heights - centre) < 1.5 * thr)
        counts[max(0, peak - 2): peak + 3] = 0
        if near.sum() < 3:
            continue
        normal, offset = _plane_fit(cand[near], up)
        inl = ~used & (np.abs(cand @ normal - offset) < thr)
        if inl.sum() >= 3:
            normal, offset = _plane_fit(cand[inl], up)
            inl = ~used & (np.abs(cand @ normal - offset) < thr)
        used |= near | inl
        if inl.sum() < min_count or normal @ up < cos_tilt:
            continue
        supports.append(_with_footprint(cand[inl], normal, offset, config.footprint_cell,
                                        float(inl.sum() * sample_voxel**2)))
    return supports


def _with_footprint(inliers, normal, offset, cell, area) -> Support:
    helper = np.array([1.0, 0, 0]) if abs(normal[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = np.cross(normal, helper)
    e1 /= np.linalg.norm(e1)
    basis = np.stack([e1, np.cross(normal, e1)])
    uv = inliers @ basis.T
    origin = uv.min(0) - cell
    idx = np.floor((uv - origin) / cell).astype(np.int64)
    grid = np.zeros(idx.max(0) + 2, bool)
    grid[idx[:, 0], idx[:, 1]] = True
    grid = ndimage.binary_fill_holes(ndimage.binary_closing(grid, iterations=2, border_value=0))
    return Support(normal, offset, len(inliers), area, origin, grid, basis)


def segment(points: np.ndarray, normals: np.ndarray, up: np.ndarray, config: AutoMaskConfig) -> AutoSegmentation:
    """Supports under the scene's ``up`` (3,) and the object clusters standing on them; see the
    module docstring."""
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    supports = find_supports(points, normals, up, config, config.sample_voxel)
    labels = np.zeros(len(points), np.int64)
    if not supports:
        facing = int((normals @ up > np.cos(np.deg2rad(config.up_max_tilt_deg))).sum())
        reason = (f"no support plane: no upward-facing surface of at least {config.min_support_area} m² "
                  f"within {config.up_max_tilt_deg:.0f}° of up ({facing} of {len(points)} surface samples face up)")
        return AutoSegmentation(points, labels, [], [], [{"reason": reason}], up)
    heights = np.stack([s.height(points) for s in supports], 1)  # (N, S)
    on_support = (np.abs(heights) < config.plane_threshold).any(1)
    above = (heights >= config.plane_threshold) & (heights <= config.max_object_height)
    for s, support in enumerate(supports):
        above[:, s] &= support.covers(points, config.footprint_cell)
    owner = np.where(above, heights, np.inf).argmin(1)
    candidate = ~on_support & above.any(1)

    objects, rejected = [], []
    next_id = 1
    for s in range(len(supports)):
        idx = np.flatnonzero(candidate & (owner == s))
        if len(idx) == 0:
            continue
        pairs = cKDTree(points[idx]).query_pairs(config.cluster_eps, output_type="ndarray")
        graph = sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(idx), len(idx)))
        _, comp = connected_components(graph, directed=False)
        sizes = np.bincount(comp)
        for c in np.argsort(-sizes, kind="stable"):
            members = idx[comp == c]
            pts = points[members]
            extent = float(np.linalg.norm(pts.max(0) - pts.min(0)))
            base_gap = float(heights[members, s].min())
            top = float(heights[members, s].max())
            info = {"support": s, "points": len(members), "extent_m": round(extent, 4),
                    "base_gap_m": round(base_gap, 4), "height_m": round(top, 4),
                    "centroid": pts.mean(0).round(4).tolist()}
            if len(members) < config.min_cluster_points:
                if len(members) >= 3:  # smaller specks are not worth a record
                    rejected.append({**info, "reason": f"{len(members)} samples (< {config.min_cluster_points})"})
                continue
            if extent > config.max_object_extent:
                rejected.append({**info, "reason": f"extent {extent:.2f} m > {config.max_object_extent} m "
                                 "(furniture or structure)"})
                continue
            if top < config.min_object_height:
                rejected.append({**info, "reason": f"top {top:.3f} m above the support (< "
                                 f"{config.min_object_height} m): a bump of the support, not an object"})
                continue
            if base_gap > config.max_base_gap:
                rejected.append({**info, "reason": f"lowest point {base_gap:.3f} m above the support "
                                 f"(> {config.max_base_gap} m): does not stand on it"})
                continue
            labels[members] = next_id
            objects.append({"id": next_id, **info})
            next_id += 1
    _reclaim_base(points, normals, labels, on_support, up, config)
    return AutoSegmentation(points, labels, supports, objects, rejected, up)


def _reclaim_base(points, normals, labels, on_support, up, config: AutoMaskConfig) -> None:
    """Give back to each object the strip of its sides within the plane threshold of the
    support (not upward-facing, next to the object's samples); the table stays table."""
    cos_tilt = np.cos(np.deg2rad(config.up_max_tilt_deg))
    strip = np.flatnonzero(on_support & (normals @ up <= cos_tilt))
    owned = np.flatnonzero(labels > 0)
    if len(strip) == 0 or len(owned) == 0:
        return
    dist, nearest = cKDTree(points[owned]).query(points[strip], distance_upper_bound=config.cluster_eps)
    found = np.isfinite(dist)
    labels[strip[found]] = labels[owned[nearest[found]]]


def auto_masks(raycaster: Raycaster, cameras: tuple[Camera, ...], seg: AutoSegmentation, sample_voxel: float):
    """Per-view masks: each pixel's first hit takes the label of the nearest sample (≤ 2 voxels away)."""
    tree = cKDTree(seg.points)
    for view, camera in enumerate(cameras):
        problem = camera_problem(camera)
        if problem:
            yield ViewFailure(view, None, problem)
            continue
        hits, _, _ = raycaster.cast_camera(camera)
        labels = np.zeros(len(hits.depth), np.int64)
        hit = np.flatnonzero(hits.hit)
        dist, nearest = tree.query(hits.points[hit], distance_upper_bound=2 * sample_voxel)
        found = np.isfinite(dist)
        labels[hit[found]] = seg.labels[nearest[found]]
        labels = labels.reshape(camera.height, camera.width)
        segments = {k: Segment(k, k) for k in map(int, np.unique(labels)) if k}
        yield ViewMasks(view, labels, segments, "auto")
