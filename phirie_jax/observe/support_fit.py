"""Support surfaces for automatic discovery (``--masks auto``), fitted on point positions.

The surface samples of a real capture's splat-derived surface are rough: only a few per cent of
their normals face up even on a table, so no support is found from per-sample normals. Here a
support is found from the samples' *positions*:

1. Seeds: the frame's support plane (``frame.support`` in the manifest, ``frame_support_plane``),
   when the frame stage found one — the one home of the support; observation refits it on the
   surface samples instead of finding another.
2. Sequential RANSAC on the sample positions (the frame's seed first): plane hypotheses from
   random triples whose normal is within ``up_max_tilt_deg`` of up, and horizontal planes
   through random samples; the one with the most samples within ``plane_threshold`` wins, is
   refitted by least squares on them (twice) and kept when it covers ``min_support_area``;
   its samples leave the pool; repeat. A plane whose samples lie mostly over an earlier
   support's footprint within ``max_object_height`` of it is not a support (a fold of a soft
   support, the flat top of what stands on it), nor is any plane within ``max_object_height``
   of the frame's support; a table over the floor is farther apart.
3. Relief (soft supports: a duvet, a cloth): the support's offset from its plane on a grid of
   ``relief_cell`` — the densest layer of the samples within ``support_relief`` of the plane in
   each cell (the support's own surface, not the sides of what stands on it or of its edge),
   cells without enough of them (under an object, never seen) filled from their nearest
   neighbours, median-smoothed, bilinear in between. Heights above the support are measured from this surface,
   so a fold of the duvet is support and an object sitting in a hollow of it stands on it.
   A flat table gets a relief of about zero.

Each support gets its 2D footprint (occupancy of its samples, holes closed: the table under an
object is never seen).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import ndimage

from phirie_jax.observe.config import AutoMaskConfig

HYPOTHESES = 256          # RANSAC hypotheses of each kind (triples, horizontal through a sample)
SCORE_SAMPLES = 40_000    # samples the hypotheses are scored on (all of them are used for the refit)
RELIEF_MIN_SAMPLES = 4    # samples a cell needs to measure its relief; others are filled in
RELIEF_SMOOTH = 3         # median filter (cells) over the relief
MAX_SUPPORTS = 4
STACKED_SHARE = 0.5  # a plane with this share of its inliers over an earlier support's footprint is stacked on it
SEED = 0
FRAME_PLANE_TILT_DEG = 5.0  # the frame's evidence plane its up came from is this close to +z


@dataclasses.dataclass(frozen=True)
class Support:
    normal: np.ndarray     # (3,) unit, pointing up
    offset: float          # plane: normal · x = offset
    inliers: int           # samples on it
    area: float            # m², samples × sample_voxel²
    origin: np.ndarray     # (2,) footprint grid origin in plane coordinates
    footprint: np.ndarray  # (U, V) bool occupancy, holes filled
    basis: np.ndarray      # (2, 3) in-plane axes
    cell: float            # footprint cell edge (m)
    relief: np.ndarray     # (P, Q) float, the support surface's offset from the plane at the centres of
                           # relief cells of edge ``relief_cell`` from ``origin`` (m); bilinear between
    relief_cell: float
    source: str = "ransac"  # "frame" (seeded by the frame's support plane) or "ransac"
    roughness: float = 0.0  # m: robust spread (1.4826 · MAD) of the samples about the support surface

    def cells(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) footprint cell of each (N, 3) point and (N,) whether it lies inside the grid."""
        uv = np.floor((points @ self.basis.T - self.origin) / self.cell).astype(np.int64)
        ok = (uv >= 0).all(1) & (uv[:, 0] < self.footprint.shape[0]) & (uv[:, 1] < self.footprint.shape[1])
        return uv, ok

    def relief_at(self, points: np.ndarray) -> np.ndarray:
        """(N,) the support surface's offset from its plane under (N, 3) points (bilinear; the
        edge cells' value beyond the grid)."""
        uv = (points @ self.basis.T - self.origin) / self.relief_cell - 0.5
        return ndimage.map_coordinates(self.relief, uv.T, order=1, mode="nearest")

    def height(self, points: np.ndarray) -> np.ndarray:
        """(N,) height of (N, 3) points above the support surface (plane + relief)."""
        return points @ self.normal - self.offset - self.relief_at(points)

    def covers(self, points: np.ndarray) -> np.ndarray:
        """(N,) whether each (N, 3) point lies over the support's footprint."""
        uv, ok = self.cells(points)
        out = np.zeros(len(points), bool)
        out[ok] = self.footprint[uv[ok, 0], uv[ok, 1]]
        return out

    def as_dict(self) -> dict:
        relief = self.relief.ravel()
        return {"normal": self.normal.round(6).tolist(), "offset": round(float(self.offset), 6),
                "inliers": self.inliers, "area_m2": round(self.area, 4), "source": self.source,
                "roughness_m": round(self.roughness, 4),
                "relief_m": [round(float(np.percentile(relief, 5)), 4), round(float(np.percentile(relief, 95)), 4)]}


def frame_support_plane(frame_record: dict | None) -> tuple[np.ndarray, float] | None:
    """The support plane the frame stage found, in the world (metres, +z up): (normal (3,),
    offset) with normal · x = offset. Read from the manifest's ``frame`` record: its ``support``
    (or ``support_plane``; world: ``{"normal", "height"}`` with normal · x = height, as the frame
    stage writes it, or ``{"normal", "offset"}``, or ``{"normal", "point"}``),
    else (a frame recorded before it had that field) the plane of its evidence
    (``evidence.planes``, capture coordinates) that its up came from — the largest within
    ``FRAME_PLANE_TILT_DEG`` of up once moved into the world. None when the frame has none."""
    frame_record = frame_record or {}
    key = next((k for k in ("support", "support_plane") if k in frame_record), None)
    try:
        if key is not None:  # the frame says which plane is the support (None: it found none)
            return _world_plane(frame_record[key]) if isinstance(frame_record[key], dict) else None
        if str(frame_record.get("up_source", "")).startswith("support plane"):
            return _evidence_plane(frame_record)
    except (TypeError, ValueError, KeyError, IndexError):
        return None
    return None


def _world_plane(support: dict) -> tuple[np.ndarray, float] | None:
    normal = np.asarray(support.get("normal", (0.0, 0.0, 1.0)), np.float64).reshape(3)
    if not np.isfinite(normal).all() or np.linalg.norm(normal) == 0:
        return None
    length = float(np.linalg.norm(normal))
    normal = normal / length
    if "offset" in support or "height" in support:  # normal · x = offset (the frame calls it height)
        offset = float(support.get("offset", support.get("height"))) / length
    elif "point" in support:
        offset = float(normal @ np.asarray(support["point"], np.float64).reshape(3))
    else:
        return None
    if not np.isfinite(offset):
        return None
    return (normal, offset) if normal[2] >= 0 else (-normal, -offset)


def _evidence_plane(frame_record: dict) -> tuple[np.ndarray, float] | None:
    """The frame's evidence plane its up came from, moved into the world by ``capture_to_world``."""
    from phirie_jax.geometry import split_sim3

    scale, rotation, translation = split_sim3(np.asarray(frame_record["capture_to_world"], np.float64))
    best = None
    for plane in frame_record.get("evidence", {}).get("planes", []):
        normal = rotation @ np.asarray(plane["normal"], np.float64)
        if normal[2] < np.cos(np.deg2rad(FRAME_PLANE_TILT_DEG)):
            continue
        offset = scale * float(plane["offset"]) + float(normal @ translation)
        if best is None or plane["inliers"] > best[2]:
            best = (normal, offset, plane["inliers"])
    return None if best is None else (best[0], best[1])


def _refit(points: np.ndarray, normal: np.ndarray, offset: float, threshold: float, up: np.ndarray,
           rounds: int = 2) -> tuple[np.ndarray, float, np.ndarray]:
    """Least-squares refit of a plane on the points within ``threshold`` of it; returns (normal,
    offset, inlier mask)."""
    inl = np.abs(points @ normal - offset) < threshold
    for _ in range(rounds):
        if inl.sum() < 3:
            break
        centre = points[inl].mean(0)
        fitted = np.linalg.svd(points[inl] - centre, full_matrices=False)[2][-1]
        fitted = fitted if fitted @ up >= 0 else -fitted
        normal, offset = fitted, float(fitted @ centre)
        inl = np.abs(points @ normal - offset) < threshold
    return normal, offset, inl


def _best_plane(points: np.ndarray, up: np.ndarray, cos_tilt: float, threshold: float, rng
                ) -> tuple[np.ndarray, float] | None:
    """The RANSAC plane (normal within the tilt of up) with the most of ``points`` within
    ``threshold``: hypotheses from triples and horizontal planes through single samples."""
    if len(points) < 3:
        return None
    score = points if len(points) <= SCORE_SAMPLES else points[rng.choice(len(points), SCORE_SAMPLES, replace=False)]
    a, b, c = (points[rng.integers(0, len(points), HYPOTHESES)] for _ in range(3))
    normals = np.cross(b - a, c - a)
    length = np.linalg.norm(normals, axis=1)
    good = length > 1e-12
    normals = normals[good] / length[good, None]
    normals *= np.where(normals @ up < 0, -1.0, 1.0)[:, None]
    upright = normals @ up >= cos_tilt
    normals, anchors = normals[upright], a[good][upright]
    through = points[rng.integers(0, len(points), HYPOTHESES)]
    normals = np.concatenate([normals, np.tile(up, (len(through), 1))])
    offsets = np.einsum("hc,hc->h", normals, np.concatenate([anchors, through]))
    best, best_count = None, -1
    for start in range(0, len(normals), 64):  # bounded memory: 64 hypotheses × the scored samples
        counts = (np.abs(score @ normals[start:start + 64].T - offsets[start:start + 64]) < threshold).sum(0)
        k = int(np.argmax(counts))
        if counts[k] > best_count:
            best, best_count = (normals[start + k], float(offsets[start + k])), int(counts[k])
    return best


def _footprint(inliers: np.ndarray, basis: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """(origin (2,), occupancy (U, V) bool with holes closed) of the inliers' plane coordinates."""
    uv = inliers @ basis.T
    origin = uv.min(0) - cell
    idx = np.floor((uv - origin) / cell).astype(np.int64)
    grid = np.zeros(idx.max(0) + 2, bool)
    grid[idx[:, 0], idx[:, 1]] = True
    return origin, ndimage.binary_fill_holes(ndimage.binary_closing(grid, iterations=2, border_value=0))


def _relief(offsets: np.ndarray, idx: np.ndarray, shape: tuple[int, int], bin_width: float) -> np.ndarray:
    """(P, Q) per-cell support offset from the samples' plane offsets (N,) in relief cells idx
    (N, 2): the median of the densest ``bin_width`` bin of a cell's offsets where it has
    ``RELIEF_MIN_SAMPLES`` (the support's own layer, not the sides of what stands on it or of the
    support's edge), else the nearest measured cell's; then a median filter."""
    flat = idx[:, 0] * shape[1] + idx[:, 1]
    order = np.lexsort((offsets, flat))
    flat, values = flat[order], offsets[order]
    cells, start, count = np.unique(flat, return_index=True, return_counts=True)
    relief = np.full(shape[0] * shape[1], np.nan)
    for cell, first, n in zip(cells, start, count):
        if n < RELIEF_MIN_SAMPLES:
            continue
        v = values[first:first + n]
        bins = np.floor((v - v[0]) / bin_width).astype(np.int64)
        densest = np.argmax(np.bincount(bins))
        relief[cell] = np.median(v[(bins >= densest - 1) & (bins <= densest + 1)])
    relief = relief.reshape(shape)
    missing = np.isnan(relief)
    if missing.all():
        return np.zeros(shape)
    if missing.any():
        nearest = ndimage.distance_transform_edt(missing, return_distances=False, return_indices=True)
        relief = relief[tuple(nearest)]
    return ndimage.median_filter(relief, size=RELIEF_SMOOTH, mode="nearest")


def _support(points: np.ndarray, near: np.ndarray, normal: np.ndarray, offset: float, config: AutoMaskConfig,
             sample_voxel: float, source: str) -> Support:
    """The support of plane (normal, offset) whose samples are ``points[near]``."""
    helper = np.array([1.0, 0, 0]) if abs(normal[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = np.cross(normal, helper)
    e1 /= np.linalg.norm(e1)
    basis = np.stack([e1, np.cross(normal, e1)])
    cell = config.footprint_cell
    members = points[near]
    origin, footprint = _footprint(members, basis, cell)
    plane_offsets = members @ normal - offset
    coarse = max(config.relief_cell, cell)
    shape = tuple(int(np.ceil(n * cell / coarse)) + 1 for n in footprint.shape)
    idx = np.floor((members @ basis.T - origin) / coarse).astype(np.int64)
    relief = (_relief(plane_offsets, idx, shape, config.plane_threshold / 2) if config.support_relief > 0
              else np.zeros(shape))
    support = Support(normal, float(offset), int(near.sum()), float(near.sum() * sample_voxel**2), origin,
                      footprint, basis, cell, relief, coarse, source)
    residual = plane_offsets - support.relief_at(members)
    roughness = float(1.4826 * np.median(np.abs(residual - np.median(residual))))
    return dataclasses.replace(support, roughness=roughness)


def _stacked(inliers: np.ndarray, normal: np.ndarray, offset: float, supports: list[Support],
             max_height: float) -> int | None:
    """The earlier support this plane (inliers (M, 3)) is a level of, else None: one whose plane
    lies within ``max_height`` of it and whose footprint holds most of its inliers (a layer of
    its relief, or the top of what stands on it: a soft duvet's folds, a big object's flat top),
    or the frame's support within ``max_height`` wherever the plane lies (the frame found the one
    support; a flat lap or shelf of what stands at its edge is not another)."""
    for k, support in enumerate(supports):
        if abs(offset - support.offset) < max_height and (
                support.source == "frame" or support.covers(inliers).mean() >= STACKED_SHARE):
            return k
    return None


def find_supports(points: np.ndarray, up: np.ndarray, config: AutoMaskConfig, sample_voxel: float,
                  seeds: tuple[tuple[np.ndarray, float], ...] = ()) -> tuple[list[Support], list[dict]]:
    """Support surfaces (largest first; the frame's seed first when it holds) of the surface
    samples (N, 3) under ``up`` (3,); also a record of every plane tried and why it was left out."""
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    cos_tilt = np.cos(np.deg2rad(config.up_max_tilt_deg))
    thr = config.plane_threshold
    band = max(thr, config.support_relief)
    min_count = config.min_support_area / sample_voxel**2
    rng = np.random.default_rng(SEED)
    free = np.ones(len(points), bool)
    supports, tried = [], []
    queue = [(np.asarray(n, np.float64), float(d), "frame") for n, d in seeds]
    while len(supports) < MAX_SUPPORTS:
        if queue:
            normal, offset, source = queue.pop(0)
        else:
            found = _best_plane(points[free], up, cos_tilt, thr, rng)
            if found is None:
                break
            (normal, offset), source = found, "ransac"
        pool = np.flatnonzero(free)
        normal, offset, inl = _refit(points[pool], normal, offset, thr, up)
        count = int(inl.sum())
        tilt = float(np.degrees(np.arccos(np.clip(normal @ up, -1.0, 1.0))))
        record = {"source": source, "normal": normal.round(6).tolist(), "offset": round(offset, 6),
                  "inliers": count, "tilt_deg": round(tilt, 2)}
        if count < min_count or normal @ up < cos_tilt:
            tried.append({**record, "reason": (f"{count} samples within {thr} m (< {min_count:.0f}: "
                                               f"{config.min_support_area} m²)") if count < min_count
                          else f"tilted {tilt:.1f}° from up (> {config.up_max_tilt_deg}°)"})
            if source == "ransac":  # the best plane left is too small or tilted: no more supports
                break
            continue
        over = _stacked(points[np.abs(points @ normal - offset) < thr], normal, offset, supports,
                        config.max_object_height)
        if over is not None:
            tried.append({**record, "reason": f"a level of support {over} ({supports[over].source}): within "
                          f"max_object_height {config.max_object_height} m of it, over its footprint or beside "
                          "the frame's support (its relief or what stands on it)"})
            free[pool[inl]] = False
            continue
        near = np.zeros(len(points), bool)
        near[pool] = np.abs(points[pool] @ normal - offset) < band
        support = _support(points, near & free, normal, offset, config, sample_voxel, source)
        free &= ~(near & support.covers(points))
        supports.append(support)
        tried.append({**record, "reason": None})
    return supports, tried
