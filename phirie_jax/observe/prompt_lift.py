"""Prompts lifted to objects and projected to every view as instance masks.

A prompt (``observe.prompts``: a box or a click in one photo) becomes an object in four steps,
all in the scene's world frame (metres, +z up, after the frame stage):

1. **Seed.** The prompt's view is rendered (depth and alpha of the Gaussians that are not
   floaters, ``observe.floaters``). In the seed window — a box's middle third, a few pixels
   around a click — the peak of the log-depth histogram is the object (the dominant depth
   cluster near the box's centre; background seen between its parts falls outside it). The
   seed is the opaque Gaussians those pixels see: projected into them, from just in front of the
   rendered depth to ``seed_behind`` behind it (haze pulls a real capture's rendered depth
   in front of its surface).
2. **Limits.** The object is what lies
   - inside the box (a click stands for the box of the depth-connected region around it, or a
     square ``click_reach`` across where that region leaks over the photo) in the prompt's
     view, with a margin, and within ``reach`` × the box's half-diagonal of the seed;
   - above its support: the flat, up-facing Gaussians under the seed's footprint peak at the
     support's height (which spans a plane's width, with most cameras above it); the object
     starts above it by the support's own spread (``support_band_min`` … ``_max``);
   - in front of the background: planes fitted (RANSAC) to the Gaussians seen in a ring just
     outside the box, oriented towards the prompt's camera; a plane the seed does not stand in
     front of is not background and is dropped.
3. **Growth.** Within those limits, the opaque Gaussians connected to the seed (closer than
   ``link_factor`` × the seed's own spacing, so the rule holds in any units) are the object.
   The more transparent Gaussians near them (``attach_factor``) follow it.
4. **Masks.** ``observe.prompt_masks`` projects the objects to every view as instance masks;
   from there the pipeline is unchanged.

Prompt k is instance k; its label is the instance's category. A prompt that cannot be lifted
(nothing opaque under it, no seed inside its limits) is recorded with the reason and the others
go on.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from phirie_jax.observe.floaters import floater_mask
from phirie_jax.observe.masks import camera_problem
from phirie_jax.observe.prompt_config import PromptConfig
from phirie_jax.observe.prompts import Prompt, camera_for
from phirie_jax.types import Camera, GaussianSplatData

FRONT = 0.01          # a pixel's Gaussians start this fraction in front of its rendered depth
PLANE_TRIALS = 200    # RANSAC hypotheses per background plane
MAX_RING = 4000       # ring Gaussians a plane is fitted to (a seeded subsample beyond it)
MIN_PLANE_GAUSSIANS = 20
SEED_IN_FRONT = 0.9   # a background plane has at least this fraction of the seed in front of it
WALL_GAP_PERCENTILE = 2   # how far an object stands in front of a plane: this percentile of its Gaussians' distances
MIN_SEED = 3          # Gaussians a seed needs
SEED_BASE = 5         # the support lies below this percentile of the seed's heights
SUPPORT_SPAN = (0.5, 0.1)  # a support spans at least these fractions of its search radius (long, short way)
CAMERAS_ABOVE = 0.9   # ... and (nearly) every camera stands above it: cameras do not stand below a support
MAD_TO_SIGMA = 1.4826
SUPPORT_SIGMAS = 2.5  # the object starts this many of the support's deviations above its height
FLOOD_SCALE = 1000.0  # log depth × this in the flood-fill image (cv2 wants absolute differences)


@dataclasses.dataclass(frozen=True)
class Solid:
    """The opaque, non-floater Gaussians objects are made of (M of them)."""

    rows: np.ndarray      # (M,) their rows in the rendered set
    points: np.ndarray    # (M, 3) centres
    normals: np.ndarray   # (M, 3) axis of the smallest scale
    flat: np.ndarray      # (M,) bool: the smallest scale is under half the middle one
    sizes: np.ndarray     # (M,) largest standard deviation

    @staticmethod
    def of(gaussians: GaussianSplatData, min_opacity: float) -> Solid:
        from phirie_jax.rotations import quat_to_matrix

        opacity = 1.0 / (1.0 + np.exp(-gaussians.opacity_logits.astype(np.float64)))
        rows = np.flatnonzero(opacity >= min_opacity)
        log_scales = gaussians.log_scales[rows].astype(np.float64)
        quats = gaussians.quats[rows].astype(np.float64)
        norms = np.linalg.norm(quats, axis=1, keepdims=True)
        quats = np.where(norms > 0, quats / np.maximum(norms, 1e-12), [1.0, 0.0, 0.0, 0.0])
        rotations = quat_to_matrix(quats)                                        # (M, 3, 3)
        axis = np.argmin(log_scales, axis=1)
        normals = rotations[np.arange(len(rows)), :, axis]
        ordered = np.sort(log_scales, axis=1)
        return Solid(rows, gaussians.means[rows].astype(np.float64), normals,
                     ordered[:, 0] - ordered[:, 1] < np.log(0.5), np.exp(ordered[:, 2]))

    def tree(self):
        from scipy.spatial import cKDTree

        return cKDTree(self.points)


@dataclasses.dataclass(frozen=True)
class LiftedPrompt:
    """Prompt ``id``'s object: ``members`` (rows of ``Solid``) and what was decided (``record``)."""

    id: int
    prompt: Prompt
    view: int
    members: np.ndarray | None      # None: the prompt could not be lifted (``record["error"]``)
    link: float                     # the connection radius its growth used
    record: dict


def rendered_set(gaussians: GaussianSplatData, config) -> tuple[GaussianSplatData, np.ndarray]:
    """The Gaussians prompts are rendered and grown over (no floaters: ``FloaterConfig``) and
    their rows in ``gaussians``."""
    keep, _ = floater_mask(gaussians.means, gaussians.log_scales, gaussians.opacity_logits, config)
    rows = np.flatnonzero(keep)
    return (gaussians if len(rows) == gaussians.num else gaussians.subset(keep)), rows


def working(camera: Camera, working_width: int) -> Camera:
    if working_width <= 0 or camera.width <= working_width:
        return camera
    return camera.scaled(working_width / camera.width)


# --- 1. the seed ----------------------------------------------------------------------------


def pixels_of(points: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rows (N,), cols (N,), depth (N,)) of world points; rows/cols −1 outside the image."""
    uv, depth = camera.project(points)
    col = np.floor(np.nan_to_num(uv[:, 0], nan=-1.0)).astype(np.int64)
    row = np.floor(np.nan_to_num(uv[:, 1], nan=-1.0)).astype(np.int64)
    outside = (depth <= 0) | (col < 0) | (row < 0) | (col >= camera.width) | (row >= camera.height)
    col[outside], row[outside] = -1, -1
    return row, col, depth


def seen_by(solid: Solid, camera: Camera, depth: np.ndarray, pixels: np.ndarray, config: PromptConfig
            ) -> np.ndarray:
    """Indices (of ``solid``) of the opaque Gaussians the ``pixels`` (H, W) bool see: projected
    into one of them, between 1 % in front of its rendered ``depth`` (H, W) and ``seed_behind``
    behind it (at most ``seed_behind_max``)."""
    row, col, z = pixels_of(solid.points, camera)
    idx = np.flatnonzero(row >= 0)
    d = depth[row[idx], col[idx]]
    behind = np.minimum(config.seed_behind * d, config.seed_behind_max)
    ok = pixels[row[idx], col[idx]] & (d > 0) & (z[idx] >= d * (1 - FRONT)) & (z[idx] <= d + behind)
    return idx[ok]


def box_in(camera: Camera, original: Camera, box) -> np.ndarray:
    """(4,) a box of the photo's pixels in the working camera's pixels."""
    return np.asarray(box, np.float64) * (camera.width / original.width)


def window(shape: tuple[int, int], box: np.ndarray | None, point: np.ndarray | None, config: PromptConfig
           ) -> np.ndarray:
    """(H, W) bool: the seed window (the box's middle, or a disk around the click)."""
    height, width = shape
    rows, cols = np.mgrid[:height, :width]
    if box is not None:
        centre, half = 0.5 * (box[:2] + box[2:]), 0.5 * config.centre_fraction * (box[2:] - box[:2])
        half = np.maximum(half, 1.0)
        return (np.abs(cols + 0.5 - centre[0]) <= half[0]) & (np.abs(rows + 0.5 - centre[1]) <= half[1])
    return np.hypot(cols + 0.5 - point[0], rows + 0.5 - point[1]) <= max(config.click_radius * width, 1.5)


def dominant_depth(depth: np.ndarray, alpha: np.ndarray, where: np.ndarray, config: PromptConfig
                   ) -> tuple[np.ndarray, float] | None:
    """(the window's pixels in its dominant depth cluster (H, W) bool, that depth), or None when
    the window shows nothing opaque."""
    usable = where & (alpha >= config.min_alpha) & (depth > 0)
    if not usable.any():
        return None
    z = np.log(depth[usable])
    edges = np.arange(z.min(), z.max() + 2 * config.depth_bin, config.depth_bin)
    counts, edges = np.histogram(z, bins=edges)
    smooth = np.convolve(counts, [1, 2, 1], mode="same")
    peak = edges[int(np.argmax(smooth))] + 0.5 * config.depth_bin
    chosen = np.zeros_like(usable)
    chosen[usable] = np.abs(z - peak) <= config.depth_band
    return chosen, float(np.exp(peak))


def implied_box(depth: np.ndarray, alpha: np.ndarray, point: np.ndarray, seed_depth: float, camera: Camera,
                floor: float | None, config: PromptConfig) -> tuple[np.ndarray, str]:
    """(4,) the box a click stands for, in working pixels, and how it was found: the bounds of the
    depth-connected region around the click (pixels whose point lies above ``floor``, the
    support's top, when known), or (when that leaks over the photo) a square ``click_reach``
    across at the seed's depth."""
    import cv2

    from phirie_jax.observe.raycast import pixel_grid, pixel_rays

    height, width = depth.shape
    usable = (alpha >= config.min_alpha) & (depth > 0)
    if floor is not None:
        origins, dirs = pixel_rays(camera, *pixel_grid(width, height))
        heights = (origins[:, 2] + depth.reshape(-1) * dirs[:, 2]).reshape(height, width)
        usable &= heights > floor
    image = np.where(usable, np.log(np.maximum(depth, 1e-9)) * FLOOD_SCALE, -1e9).astype(np.float32)
    mask = np.zeros((height + 2, width + 2), np.uint8)
    seed = (int(min(point[0], width - 1)), int(min(point[1], height - 1)))
    region = np.zeros((height, width), bool)
    if usable[seed[1], seed[0]]:
        jump = config.flood_jump * FLOOD_SCALE
        cv2.floodFill(image, mask, seed, 0, jump, jump, 4 | cv2.FLOODFILL_MASK_ONLY | (255 << 8))
        region = mask[1:-1, 1:-1] > 0
    if region.any() and region.mean() <= config.max_flood_fraction:
        ys, xs = np.nonzero(region)
        return np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], np.float64), "depth-connected region"
    half = 0.5 * config.click_reach * camera.K[0, 0] / seed_depth
    box = np.array([point[0] - half, point[1] - half, point[0] + half, point[1] + half])
    return np.clip(box, 0, [width, height, width, height]), f"{config.click_reach} m square (the region leaked)"


# --- 2. the limits --------------------------------------------------------------------------


def fit_planes(points: np.ndarray, threshold: float, config: PromptConfig, rng) -> list[tuple[np.ndarray, float, int]]:
    """Up to ``max_planes`` planes (unit normal (3,), offset d with n·x = d, inliers) of ``points``
    (N, 3), each holding ≥ ``min_plane_fraction`` of them; each plane's inliers are removed
    before the next is sought."""
    planes = []
    need = max(MIN_PLANE_GAUSSIANS, int(np.ceil(config.min_plane_fraction * len(points))))
    rest = points
    for _ in range(config.max_planes):
        if len(rest) < need:
            break
        triples = rng.integers(0, len(rest), size=(PLANE_TRIALS, 3))
        a, b, c = rest[triples[:, 0]], rest[triples[:, 1]], rest[triples[:, 2]]
        normals = np.cross(b - a, c - a)
        lengths = np.linalg.norm(normals, axis=1)
        good = lengths > 1e-12
        if not good.any():
            break
        normals = normals[good] / lengths[good, None]
        offsets = np.einsum("ij,ij->i", normals, a[good])
        counts = (np.abs(rest @ normals.T - offsets) < threshold).sum(0)
        best = int(np.argmax(counts))
        inliers = np.abs(rest @ normals[best] - offsets[best]) < threshold
        if inliers.sum() < need:
            break
        centre = rest[inliers].mean(0)
        normal = np.linalg.svd(rest[inliers] - centre, full_matrices=False)[2][-1]
        inliers = np.abs((rest - centre) @ normal) < threshold
        planes.append((normal, float(normal @ centre), int(inliers.sum())))
        rest = rest[~inliers]
    return planes


MIN_RING_PX = 3.0       # the ring around a box is at least this many pixels wide


def _grown(box: np.ndarray, width: float) -> np.ndarray:
    grow_by = np.maximum(width * (box[2:] - box[:2]), MIN_RING_PX)
    return np.concatenate([box[:2] - grow_by, box[2:] + grow_by])


def _inside(shape: tuple[int, int], box: np.ndarray) -> np.ndarray:
    rows, cols = np.mgrid[:shape[0], :shape[1]]
    x, y = cols + 0.5, rows + 0.5
    return (x >= box[0]) & (x <= box[2]) & (y >= box[1]) & (y <= box[3])


def ring_pixels(shape: tuple[int, int], box: np.ndarray, width: float) -> np.ndarray:
    """(H, W) bool: the ring just outside ``box`` (x0, y0, x1, y1), ``width`` × its size wide (at
    least ``MIN_RING_PX``)."""
    return _inside(shape, _grown(box, width)) & ~_inside(shape, box)


def outer_pixels(shape: tuple[int, int], box: np.ndarray, width: float) -> np.ndarray:
    """(H, W) bool: ``box`` and its ring."""
    return _inside(shape, _grown(box, width))


def background_planes(solid: Solid, ring: np.ndarray, camera: Camera, seed_points: np.ndarray, seed_depth: float,
                      config: PromptConfig) -> tuple[np.ndarray, list[dict]]:
    """(M,) bool: ``solid`` Gaussians behind (or on) a plane of the background seen in the ``ring``
    (indices of ``solid``), and the planes' records."""
    behind = np.zeros(len(solid.points), bool)
    rng = np.random.default_rng(0)
    if len(ring) > MAX_RING:
        ring = np.sort(rng.choice(ring, MAX_RING, replace=False))
    threshold = config.plane_threshold * seed_depth
    records = []
    for normal, offset, count in fit_planes(solid.points[ring], threshold, config, rng):
        if normal @ camera.center < offset:      # orient towards the camera: in front is positive
            normal, offset = -normal, -offset
        front = np.mean(seed_points @ normal - offset > threshold)
        record = {"normal": normal.round(4).tolist(), "offset": round(offset, 5), "gaussians": count,
                  "seed_in_front": round(float(front), 3)}
        if front >= SEED_IN_FRONT:
            behind |= solid.points @ normal - offset <= 2 * threshold
            record["used"] = True
        else:
            record["used"] = False     # the object stands in it: not background
        records.append(record)
    return behind, records


def find_support(solid: Solid, shown: np.ndarray, seed_points: np.ndarray, radius: float,
                 camera_heights: np.ndarray, config: PromptConfig) -> tuple[dict | None, str]:
    """The support under the seed (``{"height", "band", "gaussians", "span"}``) or None, and why:
    the peak height of the flat, up-facing Gaussians the prompt's view shows around it (``shown``,
    indices of ``solid``) within ``radius`` of the seed horizontally and below it."""
    centre = seed_points.mean(0)
    up = np.abs(solid.normals[:, 2]) >= np.cos(np.radians(config.support_tilt_deg))
    near = np.hypot(*(solid.points[:, :2] - centre[:2]).T) <= radius
    under = np.zeros(len(solid.points), bool)
    under[shown] = True
    under &= solid.flat & up & near & (solid.points[:, 2] < np.percentile(seed_points[:, 2], SEED_BASE))
    heights = solid.points[under, 2]
    if len(heights) < config.min_support_gaussians:
        return None, (f"{len(heights)} flat, up-facing Gaussians seen around the prompt below the seed "
                      f"(< {config.min_support_gaussians})")
    edges = np.arange(heights.min(), heights.max() + 2 * config.support_bin, config.support_bin)
    counts, edges = np.histogram(heights, bins=edges)
    smooth = np.convolve(counts, [1, 1, 1], mode="same")
    peak = int(np.argmax(smooth))
    height = float(np.median(heights[np.abs(heights - (edges[peak] + 0.5 * config.support_bin))
                                     <= 1.5 * config.support_bin]))
    layer = under.copy()
    layer[under] = np.abs(heights - height) <= 2 * config.support_bin
    if smooth[peak] < config.min_support_gaussians:
        return None, f"no height holds {config.min_support_gaussians} flat, up-facing Gaussians under the seed"
    xy = solid.points[layer, :2]
    axes = np.linalg.svd(xy - xy.mean(0), full_matrices=False)[2]
    span = np.ptp(np.percentile((xy - xy.mean(0)) @ axes.T, [5, 95], axis=0), axis=0)
    if span.max() < SUPPORT_SPAN[0] * radius or span.min() < SUPPORT_SPAN[1] * radius:
        return None, (f"the flat layer at {height:.3f} m spans {span.max():.3f} × {span.min():.3f} m (less than "
                      f"{SUPPORT_SPAN[0]} × {SUPPORT_SPAN[1]} of {radius:.3f}): not a plane under the object")
    above = float(np.mean(camera_heights > height)) if len(camera_heights) else 1.0
    if above < CAMERAS_ABOVE:
        return None, f"only {above:.0%} of the cameras stand above the flat layer at {height:.3f} m"
    near_heights = heights[np.abs(heights - height) <= config.support_band_max]
    spread = MAD_TO_SIGMA * float(np.median(np.abs(near_heights - height)))
    band = float(np.clip(SUPPORT_SIGMAS * spread, config.support_band_min, config.support_band_max))
    return {"height": round(height, 5), "band": round(band, 5), "gaussians": int(layer.sum()),
            "span": span.round(4).tolist(), "cameras_above": round(above, 3)}, "flat, up-facing Gaussians below the seed"


# --- 3. growth ------------------------------------------------------------------------------


def grow(points: np.ndarray, allowed: np.ndarray, seeds: np.ndarray, radius: float,
         reach: np.ndarray | None = None) -> np.ndarray:
    """Indices of the ``allowed`` (N,) bool points connected to a seed (indices) through steps
    shorter than ``radius``, or than either end's own ``reach`` (N,) where that is longer (a
    large Gaussian touches what lies within its extent)."""
    from scipy import sparse
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    idx = np.flatnonzero(allowed)
    start = np.flatnonzero(np.isin(idx, seeds))
    if len(start) == 0:
        return np.zeros(0, np.int64)
    tree = cKDTree(points[idx])
    pairs = [tree.query_pairs(radius, output_type="ndarray")]
    if reach is not None:
        large = np.flatnonzero(reach[idx] > radius)
        if len(large):
            found = tree.query_ball_point(points[idx[large]], reach[idx[large]])
            counts = np.array([len(f) for f in found])
            pairs.append(np.stack([np.repeat(large, counts), np.concatenate(found).astype(np.int64)], 1))
    pairs = np.concatenate(pairs)
    graph = sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(idx), len(idx)))
    _, component = connected_components(graph, directed=False)
    return idx[np.isin(component, np.unique(component[start]))]


def lift_prompt(number: int, prompt: Prompt, cameras: Sequence[Camera], gaussians: GaussianSplatData,
                solid: Solid, tree, config: PromptConfig, working_width: int) -> LiftedPrompt:
    """Prompt ``number``'s object (module docstring, steps 1–3)."""
    from phirie_jax.render import render

    view = camera_for(prompt.image, cameras)
    original = cameras[view]
    record: dict = {"id": number, **prompt.as_json(), "origin": prompt.origin, "view": view}

    def failed(reason: str) -> LiftedPrompt:
        return LiftedPrompt(number, prompt, view, None, 0.0, {**record, "error": reason})

    problem = camera_problem(original)
    if problem:
        return failed(problem)
    camera = working(original, working_width)
    out = render(gaussians.to_kernel(), camera)
    depth, alpha = np.asarray(out.depth_normalized, np.float64), np.asarray(out.alpha, np.float64)
    box = None if prompt.box is None else box_in(camera, original, prompt.box)
    point = None if prompt.point is None else box_in(camera, original, (*prompt.point, 0, 0))[:2]
    found = dominant_depth(depth, alpha, window(depth.shape, box, point, config), config)
    if found is None:
        return failed("the photo shows nothing opaque under the prompt (rendered alpha < "
                      f"{config.min_alpha})")
    pixels, seed_depth = found
    seeds = seen_by(solid, camera, depth, pixels, config)
    if len(seeds) < MIN_SEED:
        return failed(f"{len(seeds)} opaque Gaussians under the prompt (< {MIN_SEED})")
    seed_points = solid.points[seeds]
    spacing, _ = tree.query(seed_points, k=config.link_neighbours + 1)
    link = float(config.link_factor * np.median(spacing[:, -1]))
    record.update(seed={"depth": round(seed_depth, 5), "pixels": int(pixels.sum()), "gaussians": len(seeds)},
                  link=round(link, 5))
    metres_per_px = seed_depth / camera.K[0, 0]

    # the support, from what the view shows around the object (a click: within click_reach / 2)
    if box is not None:
        around, radius = box, 0.5 * float(np.hypot(*(box[2:] - box[:2]))) * metres_per_px
    else:
        half = 0.5 * config.click_reach / metres_per_px
        around, radius = np.concatenate([point - half, point + half]), 0.5 * config.click_reach
    shown = seen_by(solid, camera, depth, outer_pixels(depth.shape, around, config.ring), config)
    heights = np.array([c.center[2] for c in cameras if camera_problem(c) is None])
    support, why = find_support(solid, shown, seed_points, radius, heights, config)
    record["support"] = support or {"none": why}
    floor = None if support is None else support["height"] + support["band"]
    if box is None:
        box, how = implied_box(depth, alpha, point, seed_depth, camera, floor, config)
        record["implied_box"] = {"box": (box / (camera.width / original.width)).round(1).tolist(), "from": how}
    half_diagonal = 0.5 * float(np.hypot(*(box[2:] - box[:2]))) * metres_per_px
    record["reach"] = round(config.reach * half_diagonal, 4)

    centre = seed_points.mean(0)
    allowed = np.linalg.norm(solid.points - centre, axis=1) <= config.reach * half_diagonal
    row, col, _ = pixels_of(solid.points, camera)
    margin = config.box_margin * (box[2:] - box[:2])
    lo, hi = box[:2] - margin, box[2:] + margin
    allowed &= (row >= 0) & (col + 0.5 >= lo[0]) & (col + 0.5 <= hi[0]) & (row + 0.5 >= lo[1]) & (row + 0.5 <= hi[1])
    if floor is not None:
        allowed &= solid.points[:, 2] > floor
    ring = seen_by(solid, camera, depth, ring_pixels(depth.shape, box, config.ring), config)
    behind, planes = background_planes(solid, ring, camera, seed_points, seed_depth, config)
    allowed &= ~behind
    record["background_planes"] = planes
    extent = np.minimum(config.extent_factor * solid.sizes, config.max_link_factor * link)
    members = grow(solid.points, allowed, seeds, link, extent)
    if len(members) == 0:
        return failed("every seed Gaussian lies on the support or the background (nothing above or in front)")
    for plane in planes:
        if plane["used"]:
            distance = solid.points[members] @ np.asarray(plane["normal"]) - plane["offset"]
            plane["object_gap"] = round(float(np.percentile(distance, WALL_GAP_PERCENTILE)), 5)
    record.update(gaussians=len(members), bounds=[solid.points[members].min(0).round(4).tolist(),
                                                  solid.points[members].max(0).round(4).tolist()])
    return LiftedPrompt(number, prompt, view, members, link, record)
