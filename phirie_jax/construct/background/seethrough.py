"""Fill cells the cameras saw through: a disk where a camera saw surface behind it is in the air.

The fill region (``plane.fill_region``) is the part of the plane known from the capture (cells the
kept Gaussians cover, the object's base, the removed Gaussians of the slab, and what they
enclose) under the object's shadow. On a support that is not a flat table, a duvet draped over a
bed's edge or a cloth hanging off a table, that closure reaches past the edge into the air, and the
disks laid there hide the bed's side or the floor behind them in every view that saw it.

The capture says where that happened. For each training view whose image holds the fill cells
(``see_through_views`` of them at most, the ones that hold most cells, ties to the earlier view),
the capture G0 is rendered in a crop around the cells (``see_through_crop`` pixels a side). A
cell's centre votes *through* in a view when its pixel there is opaque (alpha ≥ ``OPAQUE_ALPHA``)
and the depth of what it shows lies more than ``see_through_depth`` behind the cell: the camera saw
past the cell's position. A cell with ``see_through_votes`` such views or more is not laid.

Under the object, the object hides the cells in every view that sees them (what the pixel shows
is in front of the cell); where the support itself or something on it is seen at the cell, the
depth is the cell's or in front of it. Neither votes, so a fill the capture leaves unseen is kept.
Every Gaussian of G0 counts, removed or kept: what a camera saw behind the cell was there.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from phirie_jax.construct.background.views import (
    Crop,
    CropImage,
    CropJob,
    CropRenderer,
    Footprints,
    ViewProjection,
    colourless,
    make_crop,
    pass_bucket,
)
from phirie_jax.types import Camera, GaussianSplatData

OPAQUE_ALPHA = 0.8    # a pixel shows a surface
MIN_CELLS = 8         # a view whose image holds fewer of the cells does not vote


@dataclasses.dataclass(frozen=True)
class SeeThrough:
    """Votes of one object's fill cells."""

    through: np.ndarray   # (M,) int: views that saw surface behind the cell
    seen: np.ndarray      # (M,) int: views in which the cell's pixel showed a surface (any depth)
    views: tuple[int, ...]  # the views that voted

    def record(self, dropped: int) -> dict:
        return {"views": len(self.views), "dropped": dropped, "cells": int(len(self.through))}


def voting_views(cameras: tuple[Camera, ...], centres: np.ndarray, max_views: int) -> list[tuple[int, np.ndarray]]:
    """(view, (M,) bool: the cell projects inside its image, in front) of the views that hold at
    least ``MIN_CELLS`` cells, the ``max_views`` that hold most."""
    held = []
    for view, camera in enumerate(cameras):
        uv, z = camera.project(centres)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
        if inside.sum() >= MIN_CELLS:
            held.append((view, inside))
    held.sort(key=lambda vi: (-int(vi[1].sum()), vi[0]))
    return held[:max_views]


def see_through_votes(data: GaussianSplatData, cameras: tuple[Camera, ...],
                      cells: list[np.ndarray], crops: CropRenderer, *, max_views: int, crop_size: int,
                      depth_tolerance: float) -> list[SeeThrough]:
    """The votes of each object's fill cell centres (``cells``: (M_i, 3) each; module docstring),
    every object's crops rendered in one pass. data: the capture G0 (N,)."""
    footprints = Footprints.of(data)
    plain = colourless(data)
    per_object, crops_made = [], []
    for centres in cells:
        views = voting_views(cameras, centres, max_views)
        per_object.append(views)
        for view, inside in views:
            uv, _ = cameras[view].project(centres[inside])
            box = np.concatenate([np.floor(uv.min(0)), np.floor(uv.max(0))])
            crops_made.append(make_crop(cameras[view], view, box, (crop_size,), margin=2))
    culled: dict[int, np.ndarray] = {}
    for view in sorted({c.view for c in crops_made}):      # the capture projected once per view
        projection = ViewProjection.of(footprints, cameras[view])
        for k, crop in enumerate(crops_made):
            if crop.view == view:
                culled[k] = projection.cull(crop.camera)[0]
    jobs = [CropJob(plain, crop, culled[k]) for k, crop in enumerate(crops_made)]
    images = iter(crops.render_many(jobs, pass_bucket([j.num for j in jobs]), num_features=1) if jobs else [])
    crop_of = iter(jobs)
    out = []
    for centres, views in zip(cells, per_object):
        through = np.zeros(len(centres), np.int64)
        seen = np.zeros(len(centres), np.int64)
        for _, inside in views:
            crop, image = next(crop_of).crop, next(images)
            opaque, behind, idx = _pixel_votes(crop, image, centres[inside], depth_tolerance)
            idx = np.flatnonzero(inside)[idx]
            seen[idx] += opaque
            through[idx] += opaque & behind
        out.append(SeeThrough(through, seen, tuple(v for v, _ in views)))
    return out


def _pixel_votes(crop: Crop, image: CropImage, centres: np.ndarray, depth_tolerance: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For the centres (P, 3) that fall on a crop pixel (their indices (Q,)): the pixel shows a
    surface (opaque, (Q,) bool), and it lies more than ``depth_tolerance`` behind the centre (Q,) bool."""
    uv, z = crop.camera.project(centres)
    col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
    ok = (z > 0) & (col >= 0) & (col < crop.size) & (row >= 0) & (row < crop.size)
    ok[ok] &= crop.inside[row[ok], col[ok]]
    r, c = row[ok], col[ok]
    opaque = image.alpha[r, c] >= OPAQUE_ALPHA
    behind = image.depth_normalized[r, c] > z[ok] + depth_tolerance
    return opaque, behind, np.flatnonzero(ok)
