"""Built-in, weight-free candidate generators that complete the hidden shape.

Each works in the gravity frame on one instance's observed points Q (and, for the
visual hull, its masks) and returns a watertight mesh in metres whose canonical frame
is the gravity frame moved so the centre of its base is the origin; the placement
(canonical → gravity frame) is known, so these candidates are scored, not searched.

- ``visual_hull``: voxels inside Q's grown box, carved by every supporting view's mask
  (``kernels.carve``) and, given the observed surface, by what the views saw through (free space
  in front of the surface they looked at), cut at the support plane, largest component, meshed.
- ``primitive``: the upright box or cylinder with the smaller footprint enclosing Q.
- ``extrude``: Q's top surface as a heightfield on its footprint, extruded down to the support.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial import ConvexHull, QhullError

from phirie_jax.construct.objects.config import ObjectsConfig
from phirie_jax.construct.objects.meshing import largest_component, occupancy_mesh
from phirie_jax.frame.gravity import GravityFrame
from phirie_jax.observe.support import Support

ABOVE_SUPPORT = 0.005   # Q points lower than this above the support may be the support's
MIN_SHAPE_POINTS = 10
MIN_VIEW_BUCKET = 8     # views are padded to a power of two, at least this (static shapes)
TRACE_COUNTS = {"carve": 0}


class GeneratorError(ValueError):
    """A generator could not make a shape for this instance (recorded as a failed candidate)."""


@dataclasses.dataclass(frozen=True)
class InstanceInput:
    """What the generators see of one instance."""

    id: int
    points: np.ndarray              # (N, 3) Q_i in the gravity frame
    frame: GravityFrame
    support: Support
    cameras: tuple                  # Camera per supporting view
    mask_paths: tuple[Path, ...]    # label image per supporting view
    labels: tuple[int, ...]         # the instance's value in each of those images
    surface: object | None = None   # the observed surface (``observe.raycast.Raycaster``), world frame


@dataclasses.dataclass(frozen=True)
class Shape:
    vertices: np.ndarray   # (V, 3) canonical (metres, +z up, base centre at the origin)
    faces: np.ndarray      # (F, 3) int64, outward
    placement: np.ndarray  # (4, 4) canonical → gravity frame (a translation)
    info: dict


def _canonical(vertices: np.ndarray, faces: np.ndarray, info: dict) -> Shape:
    lo, hi = vertices.min(0), vertices.max(0)
    base = np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), lo[2]])
    placement = np.eye(4)
    placement[:3, 3] = base
    return Shape(vertices - base, np.asarray(faces, np.int64), placement, info)


def _above(inst: InstanceInput, clearance: float = ABOVE_SUPPORT) -> np.ndarray:
    pts = inst.points[inst.points[:, 2] > inst.support.height + clearance]
    if len(pts) < MIN_SHAPE_POINTS:
        raise GeneratorError(f"{len(pts)} observed points above the support (need {MIN_SHAPE_POINTS})")
    return pts


# --- visual hull ---------------------------------------------------------------------


def _states(inst: InstanceInput, dilate_px: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(C, H, W) uint8 carve states, (C, 3, 3) K, (C, 4, 4) world-to-camera; C padded."""
    import cv2

    from kernels.carve import CARVE, INSIDE, NO_VOTE

    height = max(c.height for c in inst.cameras)
    width = max(c.width for c in inst.cameras)
    count = max(MIN_VIEW_BUCKET, 1 << max(0, len(inst.cameras) - 1).bit_length())
    states = np.full((count, height, width), NO_VOTE, np.uint8)
    Ks = np.tile(np.eye(3), (count, 1, 1))
    w2c = np.tile(np.eye(4), (count, 1, 1))
    for k, (cam, path, label) in enumerate(zip(inst.cameras, inst.mask_paths, inst.labels)):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None or image.ndim != 2 or image.shape != (cam.height, cam.width):
            continue  # an unreadable mask gives no votes (the observation stage reported it)
        mine = image == label
        if dilate_px > 0:
            mine = ndimage.binary_dilation(mine, iterations=dilate_px)
        s = np.where(image == 0, CARVE, NO_VOTE).astype(np.uint8)
        s[mine] = INSIDE
        states[k, : cam.height, : cam.width] = s
        Ks[k], w2c[k] = cam.K, cam.world_to_camera
    return states, Ks, w2c


def _traced_carve(centres, Ks, w2c, states):
    from kernels.carve import carve

    TRACE_COUNTS["carve"] += 1
    return carve(centres, Ks, w2c, states)


_carve_jit = None


def visual_hull(inst: InstanceInput, config: ObjectsConfig) -> Shape:
    import jax
    import jax.numpy as jnp

    global _carve_jit
    if not inst.cameras:
        raise GeneratorError("no supporting view with a mask")
    pts = _above(inst)
    lo, hi = np.percentile(pts, [2, 98], axis=0)
    grow = config.hull_margin + 0.2 * float(np.max(hi[:2] - lo[:2]))
    lo = np.array([lo[0] - grow, lo[1] - grow, inst.support.height])
    hi = np.array([hi[0] + grow, hi[1] + grow, hi[2] + config.hull_margin])
    res = config.hull_resolution
    voxel = float(np.max(hi - lo)) / res
    dims = np.minimum(np.ceil((hi - lo) / voxel).astype(int), res)
    grid = np.stack(np.meshgrid(*[np.arange(res)] * 3, indexing="ij"), -1).reshape(-1, 3)
    centres_g = lo + (grid + 0.5) * voxel
    states, Ks, w2c = _states(inst, config.hull_dilate_px)
    if _carve_jit is None:
        _carve_jit = jax.jit(_traced_carve)
    keep, carved = _carve_jit(jnp.asarray(inst.frame.to_world(centres_g), jnp.float32), jnp.asarray(Ks, jnp.float32),
                              jnp.asarray(w2c, jnp.float32), jnp.asarray(states))
    keep, carved = np.asarray(keep).reshape(res, res, res), np.asarray(carved).reshape(res, res, res)
    occupied = (carved <= config.hull_max_misses) & (keep >= min(2, len(inst.cameras)))
    occupied[dims[0]:, :, :] = False
    occupied[:, dims[1]:, :] = False
    occupied[:, :, dims[2]:] = False
    seen_through = free_space(inst, centres_g.reshape(res, res, res, 3), occupied, config)
    occupied &= ~seen_through
    occupied = largest_component(occupied)
    if not occupied.any():
        raise GeneratorError("every voxel was carved away (masks and cameras disagree)")
    vertices, faces = occupancy_mesh(occupied, lo + 0.5 * voxel, voxel, config.mesh_smooth)
    if len(faces) == 0:
        raise GeneratorError("the carved volume is too thin to mesh")
    return _canonical(vertices, faces, {"voxel": voxel, "views": len(inst.cameras),
                                        "voxels": int(occupied.sum()), "seen_through": int(seen_through.sum())})


def free_space(inst: InstanceInput, centres: np.ndarray, occupied: np.ndarray, config: ObjectsConfig) -> np.ndarray:
    """(R, R, R) bool: occupied voxels that at least ``hull_free_space_views`` of the instance's
    views saw through: the view's ray through the voxel centre meets the observed surface more than
    ``hull_free_space_margin`` beyond it. A silhouette cannot carve a concavity or the halo a fuzzy
    object's masks hold around its surface (a plush's fur: its masks reach ~1 cm past the surface
    its depth shows); the depth can. A ray that meets nothing votes nothing (a hole in the surface
    is no evidence of free space). All False without an observed surface."""
    out = np.zeros(occupied.shape, bool)
    if inst.surface is None or config.hull_free_space_views <= 0 or not occupied.any():
        return out
    points = inst.frame.to_world(centres[occupied])
    votes = np.zeros(len(points), np.int64)
    for camera in inst.cameras:
        offset = points - camera.center
        distance = np.linalg.norm(offset, axis=1)
        hits = inst.surface.cast(np.broadcast_to(camera.center, offset.shape).copy(),
                                 offset / np.maximum(distance, 1e-12)[:, None])
        votes += (hits.hit & (hits.depth > distance + config.hull_free_space_margin)).astype(np.int64)
    out[occupied] = votes >= config.hull_free_space_views
    return out


# --- upright primitive ----------------------------------------------------------------


def _min_area_rectangle(xy: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Smallest-area enclosing rectangle of 2D points: (angle, centre (2,), size (2,))."""
    try:
        hull = xy[ConvexHull(xy).vertices]
    except (QhullError, ValueError):
        hull = xy
    edges = np.diff(np.vstack([hull, hull[:1]]), axis=0)
    angles = np.unique(np.mod(np.arctan2(edges[:, 1], edges[:, 0]), np.pi / 2))
    best = None
    for a in angles:
        rot = np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]])  # world → rectangle axes
        p = hull @ rot.T
        lo, hi = p.min(0), p.max(0)
        area = float(np.prod(hi - lo))
        if best is None or area < best[0]:
            best = (area, a, rot.T @ (0.5 * (lo + hi)), hi - lo)
    return best[1], best[2], best[3]


def primitive(inst: InstanceInput, config: ObjectsConfig) -> Shape:
    import trimesh

    pts = _above(inst)
    height = float(np.percentile(pts[:, 2], 98) - inst.support.height)
    xy = pts[:, :2]
    angle, centre, size = _min_area_rectangle(xy)
    # Kåsa least-squares circle, radius enclosing the points
    A = np.column_stack([2 * xy, np.ones(len(xy))])
    sol, *_ = np.linalg.lstsq(A, np.sum(xy**2, 1), rcond=None)
    c_centre = sol[:2]
    radius = float(np.max(np.linalg.norm(xy - c_centre, axis=1)))
    if np.pi * radius**2 < float(np.prod(size)):
        mesh = trimesh.creation.cylinder(radius=radius, height=height, sections=48)
        mesh.apply_translation([c_centre[0], c_centre[1], inst.support.height + height / 2])
        info = {"kind": "cylinder", "radius": radius, "height": height}
    else:
        mesh = trimesh.creation.box(extents=[size[0], size[1], height])
        transform = np.eye(4)
        transform[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
        transform[:3, 3] = [centre[0], centre[1], inst.support.height + height / 2]
        mesh.apply_transform(transform)
        info = {"kind": "box", "size": [float(size[0]), float(size[1]), height]}
    return _canonical(np.asarray(mesh.vertices), np.asarray(mesh.faces), info)


# --- extruded observed surface ---------------------------------------------------------


def extrude(inst: InstanceInput, config: ObjectsConfig) -> Shape:
    cell = config.extrude_cell
    pts = _above(inst, 0.5 * ABOVE_SUPPORT)
    lo = pts[:, :2].min(0) - cell
    ij = np.floor((pts[:, :2] - lo) / cell).astype(int)
    dims = ij.max(0) + 2
    top = np.full(dims, -np.inf)
    np.maximum.at(top, (ij[:, 0], ij[:, 1]), pts[:, 2] - inst.support.height)
    seen = np.isfinite(top)
    footprint = ndimage.binary_fill_holes(ndimage.binary_closing(seen, iterations=1) | seen)
    _, (ni, nj) = ndimage.distance_transform_edt(~seen, return_indices=True)
    heights = np.where(footprint, top[ni, nj], 0.0)
    nz = int(np.ceil(heights.max() / cell))
    z_centres = (np.arange(nz) + 0.5) * cell
    occupied = footprint[:, :, None] & (z_centres[None, None, :] < heights[:, :, None])
    occupied = largest_component(occupied)
    if not occupied.any():
        raise GeneratorError("the observed surface has no extent above the support")
    origin = np.array([lo[0] + 0.5 * cell, lo[1] + 0.5 * cell, inst.support.height + 0.5 * cell])
    vertices, faces = occupancy_mesh(occupied, origin, cell, config.mesh_smooth)
    return _canonical(vertices, faces, {"cell": cell, "footprint_cells": int(footprint.sum())})


GENERATORS = {"visual_hull": visual_hull, "primitive": primitive, "extrude": extrude}
