"""Automatic instance discovery with no learned weights (``--masks auto``).

1. Sample the observed surface: first hits of pixel rays of every camera (on a stride),
   thinned to one per ``sample_voxel``, with normals turned towards the camera; which camera
   saw which sample is kept (``Samples``).
2. Supports under the scene's up (+z of the frame resolved before observation, never
   re-derived here), fitted on the samples' positions, seeded by the frame's support plane
   when the frame stage found one (``observe/support_fit.py``): planes by RANSAC, each with
   its relief (a soft support is not flat) and its 2D footprint (holes closed — the table
   under an object is never seen).
3. What stands on a support: samples above its surface (by more than the plane threshold, at
   most ``max_object_height``) inside its footprint, assigned to the nearest support below.
   Euclidean clustering (radius graph, ``cluster_eps``) per support; a cluster is an object
   when it is big enough, small enough, tall enough, its lowest point is near the support, and
   enough of the views that look at it see it (``min_views``, ``min_view_fraction``: the
   optimiser's floor bumps and floaters show in a few views only). The object's sides within
   the plane threshold of the support (not upward-facing, next to the cluster) are given back
   to it.
4. Per-view masks: each pixel's first hit on the surface takes the label of the nearest
   sample (within two sample voxels, or twice the samples' spacing where that is wider):
   projection of each cluster with occlusion. What stands above a support but became no
   object (a floater, a speck, a bump, a cluster left out) is ``UNKNOWN`` there, not 0: a pixel
   whose first hit is such an occluder says nothing about what is behind it, so it must not
   carve an object's visual hull away (0 = the support or the scene around it: nothing there).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from phirie_jax.observe.config import AutoMaskConfig
from phirie_jax.observe.masks import Segment, ViewFailure, ViewMasks, camera_problem
from phirie_jax.observe.raycast import Raycaster
from phirie_jax.observe.support_fit import Support, find_supports
from phirie_jax.observe.surface import pack_keys
from phirie_jax.types import Camera

UNKNOWN = 65535  # mask value of a pixel seen on something above a support that is no object; never an
                 # instance (no segment, nothing lifted): consumers that ask "this instance?" see another
                 # label, and the visual hull does not carve there (it carves on 0 only)
HIDDEN_MARGIN = 0.5  # a view looks at a cluster unless the surface stops its centre's ray this fraction of
                     # the cluster's radius short of the cluster


@dataclasses.dataclass(frozen=True)
class Samples:
    """The observed surface, sampled: one sample per voxel, and which camera's rays hit which."""

    points: np.ndarray      # (N, 3) surface samples
    normals: np.ndarray     # (N, 3) unit, facing a camera that saw them
    hit_sample: np.ndarray  # (H,) int64 sample of each ray hit
    hit_camera: np.ndarray  # (H,) int64 camera (index into the cameras sampled) of each ray hit
    cameras: int            # cameras sampled


@dataclasses.dataclass(frozen=True)
class AutoSegmentation:
    points: np.ndarray      # (N, 3) observed surface samples
    labels: np.ndarray      # (N,) int64 object id per sample, 0 = support or nothing
    supports: list[Support]
    objects: list[dict]     # accepted clusters: id, support, points, extent, base gap, views
    rejected: list[dict]    # clusters left out, with the reason
    up: np.ndarray          # (3,)
    planes: list[dict] = dataclasses.field(default_factory=list)  # every support plane tried, and why not
    unknown: np.ndarray | None = None  # (N,) bool: above a support and no object's (``UNKNOWN`` in masks)


def observed_samples(raycaster: Raycaster, cameras: list[Camera], stride: int, voxel: float) -> Samples:
    """The surface the cameras see, one sample per voxel (see ``Samples``)."""
    points, normals, owner = [], [], []
    for k, cam in enumerate(cameras):
        hits, _, _ = raycaster.cast_camera(cam, stride)
        points.append(hits.points[hits.hit])
        normals.append(hits.normal[hits.hit])
        owner.append(np.full(int(hits.hit.sum()), k, np.int64))
    points, normals, owner = np.concatenate(points), np.concatenate(normals), np.concatenate(owner)
    _, first, inverse = np.unique(pack_keys(np.floor(points / voxel)), return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")            # samples in the order their voxel was first seen
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return Samples(points[first[order]], normals[first[order]], rank[inverse.ravel()], owner, len(cameras))


def view_counts(samples: Samples, labels: np.ndarray, count: int, min_pixels: int) -> np.ndarray:
    """(count + 1,) per label 0..count: how many cameras have ≥ ``min_pixels`` ray hits on its samples."""
    hit_label = labels[samples.hit_sample]
    on = hit_label > 0
    pairs = np.bincount(hit_label[on] * samples.cameras + samples.hit_camera[on],
                        minlength=(count + 1) * samples.cameras).reshape(count + 1, samples.cameras)
    return (pairs >= min_pixels).sum(1)


def looking_views(raycaster: Raycaster | None, cameras: list[Camera], centre: np.ndarray, radius: float) -> int:
    """Cameras that look at a cluster: its centre (3,) in the image, in front, and (with a
    ``raycaster``) the surface not stopping the centre's ray well before the cluster."""
    looking = []
    for cam in cameras:
        uv, depth = cam.project(centre[None])
        if depth[0] > 0 and 0 <= uv[0, 0] < cam.width and 0 <= uv[0, 1] < cam.height:
            looking.append(cam)
    if raycaster is None or not looking:
        return len(looking)
    origins = np.array([c.center for c in looking], np.float64)
    dirs = centre[None] - origins
    hits = raycaster.cast(origins, dirs)  # depth in units of the whole segment to the centre
    dist = np.linalg.norm(dirs, axis=1)
    hidden = hits.depth * dist < dist - radius * (1 + HIDDEN_MARGIN)
    return int((~hidden).sum())


def segment(samples: Samples, up: np.ndarray, config: AutoMaskConfig, cameras: list[Camera] | None = None,
            raycaster: Raycaster | None = None, seeds: tuple = (), scale_uncertainty: float = 1.0
            ) -> AutoSegmentation:
    """Supports under the scene's ``up`` (3,) (``seeds``: (normal, offset) planes the frame found)
    and the object clusters standing on them; see the module docstring. ``cameras``: the cameras
    ``samples`` were taken with (their views count clusters' viewers; None: no view filter);
    ``raycaster``: the surface, to tell which cameras have a cluster hidden. ``scale_uncertainty``:
    the frame's (multiplicative) — a cluster is furniture only when it is larger than
    ``max_object_extent`` at every scale the frame allows."""
    points, normals = samples.points, samples.normals
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    supports, planes = find_supports(points, up, config, config.sample_voxel, seeds)
    labels = np.zeros(len(points), np.int64)
    if not supports:
        reason = (f"no support plane: no plane within {config.up_max_tilt_deg:.0f}° of up holds "
                  f"{config.min_support_area} m² of the {len(points)} surface samples within "
                  f"{config.plane_threshold} m" + (f" (seeded by the frame's plane: {planes[0]['reason']})"
                                                   if planes and planes[0]["source"] == "frame" else ""))
        return AutoSegmentation(points, labels, [], [], [{"reason": reason}], up, planes)
    heights = np.stack([s.height(points) for s in supports], 1)  # (N, S)
    on_support = (np.abs(heights) < config.plane_threshold).any(1)
    above = (heights >= config.plane_threshold) & (heights <= config.max_object_height)
    for s, support in enumerate(supports):
        above[:, s] &= support.covers(points)
    owner = np.where(above, heights, np.inf).argmin(1)
    candidate = ~on_support & above.any(1)

    clusters, rejected = [], []
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
            if extent > config.max_object_extent * scale_uncertainty:
                rejected.append({**info, "reason": f"extent {extent:.2f} m > {config.max_object_extent} m "
                                 + (f"× the frame's scale uncertainty {scale_uncertainty:.2f} "
                                    if scale_uncertainty > 1 else "") + "(furniture or structure)"})
                continue
            if top < config.min_object_height:
                rejected.append({**info, "reason": f"top {top:.3f} m above the support (< "
                                 f"{config.min_object_height} m): a bump of the support, not an object"})
                continue
            if base_gap > config.max_base_gap:
                rejected.append({**info, "reason": f"lowest point {base_gap:.3f} m above the support "
                                 f"(> {config.max_base_gap} m): does not stand on it"})
                continue
            clusters.append((members, info))
    objects = _seen_enough(samples, clusters, labels, config, cameras, raycaster, rejected)
    _reclaim_base(points, normals, labels, on_support, up, config)
    over = ~on_support & np.stack([(heights[:, s] >= config.plane_threshold) & support.covers(points)
                                   for s, support in enumerate(supports)], 1).any(1)
    return AutoSegmentation(points, labels, supports, objects, rejected, up, planes, over & (labels == 0))


def _seen_enough(samples: Samples, clusters: list, labels: np.ndarray, config: AutoMaskConfig,
                 cameras: list[Camera] | None, raycaster: Raycaster | None, rejected: list[dict]) -> list[dict]:
    """Label the clusters that enough views see (``min_views``, ``min_view_fraction``) 1, 2, …
    in ``labels``; record the others in ``rejected``. Returns the objects' records."""
    trial = np.zeros_like(labels)
    for k, (members, _) in enumerate(clusters, start=1):
        trial[members] = k
    seen = view_counts(samples, trial, len(clusters), config.min_view_pixels)
    objects, next_id = [], 1
    for k, (members, info) in enumerate(clusters, start=1):
        views = int(seen[k])
        info = {**info, "views": views}
        if cameras is not None:
            pts = samples.points[members]
            centre = pts.mean(0)
            radius = float(np.percentile(np.linalg.norm(pts - centre, axis=1), 90))
            looking = looking_views(raycaster, cameras, centre, radius)
            info["looking_views"] = looking
            fraction = views / max(looking, 1)
            if views < config.min_views:
                rejected.append({**info, "reason": f"seen by {views} views (< min_views {config.min_views})"})
                continue
            if fraction < config.min_view_fraction:
                rejected.append({**info, "reason": f"seen by {views} of the {looking} views that look at it "
                                 f"({fraction:.2f} < min_view_fraction {config.min_view_fraction})"})
                continue
        labels[members] = next_id
        objects.append({"id": next_id, **info})
        next_id += 1
    return objects


def _reclaim_base(points, normals, labels, on_support, up, config: AutoMaskConfig) -> None:
    """Give back to each object the strip of its sides within the plane threshold of the
    support (not upward-facing, next to the object's samples); the table stays table."""
    cos_tilt = np.cos(np.deg2rad(config.up_max_tilt_deg))
    strip = np.flatnonzero(on_support & (normals @ up <= cos_tilt))
    owned = np.flatnonzero(labels > 0)
    if len(strip) == 0 or len(owned) == 0:
        return
    dist, nearest = cKDTree(points[owned]).query(points[strip], distance_upper_bound=config.cluster_eps,
                                                         workers=-1)
    found = np.isfinite(dist)
    labels[strip[found]] = labels[owned[nearest[found]]]


def label_radius(points: np.ndarray, sample_voxel: float) -> float:
    """How far a pixel's first hit may be from the sample whose label it takes: two sample voxels, or
    twice the samples' median spacing where the rays sampled the surface more sparsely (small
    images: a pixel is wider than a voxel at the cameras' distance)."""
    if len(points) < 2:
        return 2 * sample_voxel
    spacing, _ = cKDTree(points).query(points, k=2, workers=-1)
    return max(2 * sample_voxel, 2 * float(np.median(spacing[:, 1])))


def auto_masks(raycaster: Raycaster, cameras: tuple[Camera, ...], seg: AutoSegmentation, sample_voxel: float):
    """Per-view masks: each pixel's first hit takes the label of the nearest sample (``label_radius``);
    ``UNKNOWN`` where that sample stands above a support and is no object's (``seg.unknown``)."""
    tree = cKDTree(seg.points)
    radius = label_radius(seg.points, sample_voxel)
    sample_labels = seg.labels if seg.unknown is None else np.where(seg.unknown, UNKNOWN, seg.labels)
    for view, camera in enumerate(cameras):
        problem = camera_problem(camera)
        if problem:
            yield ViewFailure(view, None, problem)
            continue
        hits, _, _ = raycaster.cast_camera(camera)
        labels = np.zeros(len(hits.depth), np.int64)
        hit = np.flatnonzero(hits.hit)
        dist, nearest = tree.query(hits.points[hit], distance_upper_bound=radius, workers=-1)
        found = np.isfinite(dist)
        labels[hit[found]] = sample_labels[nearest[found]]
        labels = labels.reshape(camera.height, camera.width)
        segments = {k: Segment(k, k) for k in map(int, np.unique(labels)) if k and k != UNKNOWN}
        yield ViewMasks(view, labels, segments, "auto")
