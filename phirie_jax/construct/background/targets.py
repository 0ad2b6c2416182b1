"""Inpainting targets: one primary view per object, every edit of a frame in one target.

Primary view of an object: the camera that sees its fill region largest and sharpest — the
projected area in pixels of its fill cells (in front of the camera and inside the image; the
image-space resolution on the exposed footprint), times a blur factor when the captured
images are available (variance of the Laplacian inside that area relative to the median of
the five best views, capped at 1). Objects whose primary views coincide share that *frame*
where their regions fit together in one crop of the pass's size at full resolution (else each
has its own crop of that view).

A frame is a crop around all of its objects' regions (``views``). In it, rendered once (the
five passes of every frame in batched launches of one program: ``plan_frame``,
``render_plans``, then ``finish_frame`` on the host):

- the capture G0 with the removed Gaussians' indicator as a feature: their composited weight
  is the *region* (≥ ``region_weight``, grown by ``region_dilate_px``) — every removed object's,
  so one object's target never shows another removed object (the composite target);
- the kept Gaussians, as three layers around the new disks (``kernels.fill``: front, slab,
  back; ``split_layers``), which compose the kept render;
- the initial disks: where they are opaque and the kept surface lies behind them (seen through
  the hole), or where the kept render is not opaque, the region is a *hole*.

Target = the kept render with the hole inpainted: by default with known patches of the image
around it (``exemplar``: the support's texture continues through the hole), or by OpenCV's
diffusion (Telea or Navier–Stokes, per channel at 16 bits: ``inpaint``). Region pixels the kept
scene already explains (the tabletop seen behind the object from this side) keep their rendered
colour. The loss mask is the region grown by ``loss_ring_px`` (inside the image).

External editor targets (``TargetsConfig.external`` = a folder). Per frame, files named by
the camera's image stem:

    <stem>.png       the edited image: RGB, 8 or 16 bit, the camera's full image size;
                     only pixels under the mask are used
    <stem>_mask.png  optional: 8/16-bit, non-zero = fit these pixels (default: our loss mask)

A stem matching a primary view replaces our target there; other stems add frames. The
folder ``background/targets/`` that a run writes (``TargetsConfig.write``) has this layout (plus
``<stem>_hole.png``, the inpainted pixels; the manifest's ``background.targets`` lists the
frames), so an editor can start from it and hand it back.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import numpy as np
from scipy import ndimage

from kernels.raster import RasterConfig
from phirie_jax.construct.background.config import BackgroundConfig, TargetsConfig
from phirie_jax.construct.background.exemplar import exemplar_inpaint
from phirie_jax.construct.background.views import (
    Crop,
    CropImage,
    CropJob,
    CropRenderer,
    Footprints,
    baked,
    colourless,
    cull,
    pass_bucket,
    screen_radius_bound,
    tile_rects,
)
from phirie_jax.errors import SceneInputError
from phirie_jax.types import Camera, GaussianSplatData

SHARPNESS_CANDIDATES = 5  # views whose blur is measured for the primary choice
FILL_ALPHA = 0.5          # the initial disks cover a pixel
SUPPORT_ALPHA = 0.9       # a pixel shows the support: its slab this opaque, the front this clear
DEPTH_MARGIN_SIGMAS = 3.0  # the slab's depth band: the disks' depths ± this many (largest) σ plus one cell
DEPTH_ORDER_SLACK = 1e-3   # relative: a kept Gaussian this close behind a removed one may sort before it on the
                           # device (float32 depths), so it stays in the removed-weight render


@dataclasses.dataclass(frozen=True)
class PrimaryView:
    object_id: int
    view: int
    pixels: float      # projected fill area, px
    sharpness: float   # blur factor in (0, 1]

    def as_dict(self, cameras: tuple[Camera, ...]) -> dict:
        return {"view": self.view, "name": cameras[self.view].name, "pixels": round(self.pixels, 1),
                "sharpness": round(self.sharpness, 3)}


def _image(camera: Camera) -> np.ndarray | None:
    """The captured image (H, W, 3) float RGB, or None."""
    if camera.image_path is None or not Path(camera.image_path).is_file():
        return None
    return _read_rgb(Path(camera.image_path), camera.width, camera.height)


def _read_rgb(path: Path, width: int, height: int) -> np.ndarray | None:
    """The image file (height, width, 3) float RGB, or None when unreadable or of another size."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.shape[:2] != (height, width):
        return None
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    return img[..., 2::-1].astype(np.float32) / scale


def _grey(camera: Camera) -> np.ndarray | None:
    """The captured image in grey (H, W) float32, or None; each file decoded once while it is
    unchanged (the objects of a scene share their candidate views)."""
    if camera.image_path is None or not Path(camera.image_path).is_file():
        return None
    stat = Path(camera.image_path).stat()
    return _grey_file(str(camera.image_path), stat.st_mtime_ns, stat.st_size, camera.width, camera.height)


@functools.lru_cache(maxsize=64)
def _grey_file(path: str, mtime_ns: int, size: int, width: int, height: int) -> np.ndarray | None:
    """(Cached by the file's path, modification time and size.) Read-only."""
    import cv2

    img = _read_rgb(Path(path), width, height)
    if img is None:
        return None
    grey = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    grey.setflags(write=False)
    return grey


def _box(uv: np.ndarray, radius: np.ndarray, camera: Camera) -> np.ndarray | None:
    """Inclusive pixel box of discs (uv, radius) clipped to the image, or None when outside."""
    lo = np.floor(np.min(uv - radius[:, None], axis=0))
    hi = np.floor(np.max(uv + radius[:, None], axis=0))
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, [camera.width - 1, camera.height - 1])
    return None if np.any(hi < lo) else np.concatenate([lo, hi]).astype(np.int64)


def choose_primary(object_id: int, centres: np.ndarray, normal: np.ndarray, cameras: tuple[Camera, ...],
                   grid: float) -> PrimaryView | None:
    """The object's primary view (module docstring), or None when no camera sees its fill."""
    import cv2

    scored = []
    for view, cam in enumerate(cameras):
        uv, z = cam.project(centres)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        if not inside.any():
            continue
        rays = centres[inside] - cam.center
        dist = np.linalg.norm(rays, axis=1)
        cos = np.abs(rays @ normal) / np.maximum(dist, 1e-12)
        focal = float(np.sqrt(abs(np.linalg.det(cam.K[:2, :2]))))
        area = np.sum((focal * grid) ** 2 * cos * dist / z[inside] ** 3)  # px² per cell, foreshortened
        scored.append((float(area), view, uv[inside]))
    if not scored:
        return None
    scored.sort(key=lambda s: -s[0])
    best = scored[:SHARPNESS_CANDIDATES]
    sharp = []
    for _, view, uv in best:
        grey = _grey(cameras[view])
        box = _box(uv, np.zeros(len(uv)), cameras[view])
        if grey is None or box is None:
            sharp.append(np.nan)
            continue
        patch = grey[box[1]:box[3] + 1, box[0]:box[2] + 1]
        sharp.append(float(cv2.Laplacian(patch, cv2.CV_32F).var()) if patch.size >= 9 else np.nan)
    sharp = np.asarray(sharp)
    med = np.nanmedian(sharp) if np.isfinite(sharp).any() else np.nan
    factor = np.where(np.isfinite(sharp) & (med > 0), np.minimum(1.0, sharp / max(med, 1e-12)), 1.0)
    k = int(np.argmax([s[0] * f for s, f in zip(best, factor)]))
    return PrimaryView(object_id, best[k][1], best[k][0], float(factor[k]))


@dataclasses.dataclass
class Frame:
    """One target crop and everything the fit needs from it."""

    view: int
    crop: Crop
    objects: list[int]
    region: np.ndarray       # (C, C) bool
    hole: np.ndarray         # (C, C) bool: inpainted pixels
    mask: np.ndarray         # (C, C) float32 loss weights (inside ``reach``)
    kept_rgb: np.ndarray     # (C, C, 3) the kept scene, rendered
    target: np.ndarray       # (C, C, 3)
    front_rgb: np.ndarray    # (C, C, 3)
    front_trans: np.ndarray  # (C, C)
    back_rgb: np.ndarray     # (C, C, 3)
    reach: np.ndarray        # (C, C) bool: pixels the frame's own disks can touch
    slab: GaussianSplatData  # kept Gaussians of the disks' depth band touching ``reach``, colour baked (SH DC)
    source: str              # "exemplar" | "telea" | "ns" | "external"

    def record(self, cameras: tuple[Camera, ...]) -> dict:
        return {"view": self.view, "name": cameras[self.view].name, "objects": self.objects,
                "crop": {"origin": list(self.crop.origin), "size": self.crop.size, "scale": round(self.crop.scale, 4)},
                "region_px": int(self.region.sum()), "hole_px": int(self.hole.sum()),
                "loss_px": int((self.mask > 0).sum()), "slab_gaussians": self.slab.num, "source": self.source}


def inpaint(image: np.ndarray, hole: np.ndarray, method: str, radius: int, source: np.ndarray | None = None
            ) -> np.ndarray:
    """(H, W, 3) float image in [0, 1] with the ``hole`` (H, W) bool pixels filled: "exemplar"
    copies known patches (``exemplar``: the support's texture continues; patches come from the
    ``source`` (H, W) bool pixels, default every known one; what no patch can reach is diffused
    by Telea), "telea" / "ns" diffuse the border inwards (OpenCV; ``radius`` is their neighbourhood).

    OpenCV's methods run per channel at 16 bits: OpenCV's Telea returns garbage for float32 input (measured with
    OpenCV 4.x: values far outside the input range), and 8 bits would quantize the target.
    Pixels outside the hole are returned unchanged.
    """
    import cv2

    image = np.clip(np.asarray(image, np.float32), 0.0, 1.0)
    if not hole.any():
        return image.copy()
    if method == "exemplar":
        image, hole = exemplar_inpaint(image, hole, source)
        if not hole.any():
            return image
        method = "telea"
    flag = cv2.INPAINT_TELEA if method == "telea" else cv2.INPAINT_NS
    m = hole.astype(np.uint8) * 255
    channels = [cv2.inpaint(np.round(image[..., c] * 65535).astype(np.uint16), m, radius, flag)
                for c in range(3)]
    filled = np.stack(channels, axis=-1).astype(np.float32) / 65535.0
    return np.where(hole[..., None], filled, image)


def read_external(folder: Path, camera: Camera) -> tuple[np.ndarray, np.ndarray | None] | None:
    """An editor's target (H, W, 3) float and mask (H, W) bool or None for this camera, or None."""
    import cv2

    stem = Path(camera.name).stem
    path = folder / f"{stem}.png"
    if not path.is_file():
        return None
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 3 or img.shape[:2] != (camera.height, camera.width):
        raise SceneInputError(path, "image", f"expected an RGB image of {camera.width}×{camera.height} "
                              f"(camera {camera.name}), got {None if img is None else img.shape}")
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    target = img[..., 2::-1].astype(np.float32) / scale
    mask_path = folder / f"{stem}_mask.png"
    mask = None
    if mask_path.is_file():
        m = cv2.imread(str(mask_path), cv2.IMREAD_UNCHANGED)
        if m is None or m.shape[:2] != (camera.height, camera.width):
            raise SceneInputError(mask_path, "image", f"expected a mask of {camera.width}×{camera.height}")
        mask = (m if m.ndim == 2 else m[..., 0]) > 0
    return target, mask


def external_views(folder: Path, cameras: tuple[Camera, ...]) -> list[int]:
    """Camera indices with a target in the editor's folder."""
    if not folder.is_dir():
        raise SceneInputError(folder, "targets", "not a folder (expected <image stem>.png files)")
    return [k for k, cam in enumerate(cameras) if (folder / f"{Path(cam.name).stem}.png").is_file()]


def frame_box(camera: Camera, disks: GaussianSplatData, removed: GaussianSplatData) -> np.ndarray | None:
    """Pixel box of a frame: its objects' disks and removed Gaussians (their 3σ discs)."""
    parts = [d for d in (disks, removed) if d.num]
    if not parts:
        return None
    uv = np.concatenate([screen_radius_bound(d, camera)[0] for d in parts])
    z = np.concatenate([screen_radius_bound(d, camera)[1] for d in parts])
    r = np.concatenate([screen_radius_bound(d, camera)[2] for d in parts])
    front = z > 0
    return _box(uv[front], r[front], camera) if front.any() else None


def split_layers(data: GaussianSplatData, camera: Camera, kept_idx: np.ndarray, disks: GaussianSplatData,
                 normals: np.ndarray, slab: float, reach_z: float, kept_z: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kept indices of the front, slab and back layers around the disks in this camera.

    By view depth against the disks' band [min − reach_z, max + reach_z] (the renderer sorts by
    centre depth, so outside the band the order is exact); inside the band by the signed height
    over the nearest disk's plane: within ``slab`` is slab, on the camera's side front, else back
    (a table's underside, a few cm below, is back although its depth is in the band). kept_z: (K,)
    the view depths of ``kept_idx`` when the caller has them (``screen_radius_bound``'s).
    """
    from scipy.spatial import cKDTree

    z = screen_radius_bound(data.subset(kept_idx), camera)[1] if kept_z is None else kept_z
    if disks.num == 0:
        return kept_idx, kept_idx[:0], kept_idx[:0]
    _, zd, _ = screen_radius_bound(disks, camera)
    zd = zd[zd > 0]
    if len(zd) == 0:
        return kept_idx, kept_idx[:0], kept_idx[:0]
    lo, hi = float(zd.min()) - reach_z, float(zd.max()) + reach_z
    in_band = (z >= lo) & (z <= hi)
    band = kept_idx[in_band]
    _, nn = cKDTree(disks.means.astype(np.float64)).query(data.means[band].astype(np.float64), workers=-1)
    centre, normal = disks.means[nn].astype(np.float64), normals[nn]
    h = np.sum((data.means[band] - centre) * normal, axis=1)
    side = np.sign(np.sum((camera.center - centre) * normal, axis=1))
    is_slab = np.abs(h) <= slab
    is_front = ~is_slab & (h * side > 0)
    front = np.concatenate([kept_idx[z < lo], band[is_front]])
    back = np.concatenate([kept_idx[z > hi], band[~is_slab & ~is_front]])
    return np.sort(front), band[is_slab], np.sort(back)


def disk_reach(disks: GaussianSplatData, crop: Crop, max_sigma: float, max_offset: float) -> np.ndarray:
    """(C, C) bool: crop pixels a disk can touch while it is fitted (its largest σ, moved by its
    largest offset): a disc of the kernel's radius bound around each projected centre."""
    import cv2

    grown = dataclasses.replace(disks, log_scales=np.full_like(disks.log_scales, np.log(max_sigma)))
    uv, z, r = screen_radius_bound(grown, crop.camera)
    focal = float(max(abs(crop.camera.K[0, 0]), abs(crop.camera.K[1, 1])))
    r = r + focal * max_offset / np.maximum(z, 1e-6)
    canvas = np.zeros((crop.size, crop.size), np.uint8)
    for (x, y), rad in zip(uv[z > 0], r[z > 0]):
        if -rad <= x <= crop.size + rad and -rad <= y <= crop.size + rad:
            cv2.circle(canvas, (round(x), round(y)), int(np.ceil(rad)) + 1, 1, -1)
    return canvas.astype(bool)


def touching(data: GaussianSplatData, crop: Crop, reach: np.ndarray) -> np.ndarray:
    """(N,) bool: the Gaussian's radius bound meets a reachable pixel (a superset)."""
    if not reach.any() or data.num == 0:
        return np.zeros(data.num, bool)
    uv, z, r = screen_radius_bound(data, crop.camera)
    dist = ndimage.distance_transform_edt(~reach)
    px = np.clip(np.floor(uv), 0, crop.size - 1)
    off = np.linalg.norm(uv - (px + 0.5), axis=1)  # from the centre to the nearest crop pixel centre
    d = dist[px[:, 1].astype(np.int64), px[:, 0].astype(np.int64)]
    return (z > 0) & (d - off <= r + 1.0)


@dataclasses.dataclass(frozen=True)
class _KeptRender:
    """The kept scene in one crop, composed from its three layers (every array (C, C) or (C, C, 3))."""

    rgb: np.ndarray          # (C, C, 3)
    alpha: np.ndarray        # (C, C)
    depth: np.ndarray        # (C, C) expected depth, inf where nothing is rendered
    front_rgb: np.ndarray    # (C, C, 3)
    front_trans: np.ndarray  # (C, C)
    back_rgb: np.ndarray     # (C, C, 3)


def _compose_kept(r_front: CropImage, r_slab: CropImage, r_back: CropImage) -> _KeptRender:
    """Front, slab and back renders composited front to back (the renderer's Σ wᵢ zᵢ per layer)."""
    f_rgb, f_t = r_front.rgb, 1.0 - r_front.alpha
    s_rgb, s_t = r_slab.rgb, 1.0 - r_slab.alpha
    b_rgb = r_back.rgb
    rgb = f_rgb + f_t[..., None] * (s_rgb + s_t[..., None] * b_rgb)
    alpha = 1.0 - f_t * s_t * (1.0 - r_back.alpha)
    depth_sum = r_front.depth + f_t * (r_slab.depth + s_t * r_back.depth)
    depth = np.where(alpha > 0, depth_sum / np.maximum(alpha, 1e-10), np.inf)
    return _KeptRender(rgb, alpha, depth, f_rgb, f_t, b_rgb)


def _region_hole_mask(removed_weight: np.ndarray, kept: _KeptRender, r_disks: CropImage, crop: Crop,
                      config: TargetsConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(C, C) bool region, hole and loss mask of a frame from the removed Gaussians' composited
    weight ``removed_weight`` (C, C), the kept render and the initial disks' render (module docstring)."""
    region = removed_weight >= config.region_weight
    if config.region_dilate_px > 0:
        region = ndimage.binary_dilation(region, iterations=config.region_dilate_px)
    region &= crop.inside
    on_disks = r_disks.alpha >= FILL_ALPHA
    see_through = kept.depth > r_disks.depth_normalized + config.plane_depth_tolerance
    # only where new disks will be can the target differ from the kept render
    hole = region & on_disks & ((kept.alpha < config.explained_alpha) | see_through)
    mask = ndimage.binary_dilation(region, iterations=config.loss_ring_px) if config.loss_ring_px > 0 else region
    return region, hole, mask & crop.inside


def removed_weight_subset(removed: np.ndarray, uv: np.ndarray, z: np.ndarray, r: np.ndarray, size: int,
                          tile: int) -> np.ndarray:
    """(K,) bool over a crop's culled Gaussians: those the composited weight of the removed ones
    depends on. removed: (K,) bool; uv (K, 2), z (K,), r (K,): their pixel centres, view depths and
    radius bounds (``screen_radius_bound``) in the C × C crop (C = ``size``, ``tile``-pixel tiles).

    The kernel composites each tile's Gaussians in the order of their centre depths, and a pixel
    sees only its tile's; so the removed weight at every pixel depends only on the removed
    Gaussians and the kept ones that share a tile with one and sort before the deepest removed
    one there. Those are kept here (their tiles from the radius bound hold the kernel's; a kept
    one within ``DEPTH_ORDER_SLACK`` behind is kept too: the device's depths are float32); the
    render of the subset has the full render's removed weight (up to the float rounding of its
    chunked compositing), not its colour or depth."""
    keep = removed.copy()
    rem, kept = np.flatnonzero(removed), np.flatnonzero(~removed)
    if len(rem) == 0 or len(kept) == 0:
        return keep
    x0, x1, y0, y1 = tile_rects(uv, r, size, tile)
    for ty in range(-(-size // tile)):
        row_rem = rem[(y0[rem] <= ty) & (y1[rem] >= ty)]
        if len(row_rem) == 0:
            continue
        row_kept = kept[(y0[kept] <= ty) & (y1[kept] >= ty)]
        for tx in range(-(-size // tile)):
            here = row_rem[(x0[row_rem] <= tx) & (x1[row_rem] >= tx)]
            if len(here) == 0:
                continue
            deepest = float(z[here].max())
            near = row_kept[(x0[row_kept] <= tx) & (x1[row_kept] >= tx)]
            keep[near[z[near] <= deepest + DEPTH_ORDER_SLACK * abs(deepest)]] = True
    return keep


@dataclasses.dataclass(frozen=True)
class FramePlan:
    """One frame before any render: its five passes (``CropJob`` each) and what finishing needs.

    Passes, in order: the capture with the removed Gaussians' indicator as a feature (``full``:
    only its removed weight is read, so it renders only the Gaussians that weight depends on,
    ``removed_weight_subset``, without colour), the kept front, back and slab layers (their colour
    in this view baked into the SH DC: ``views.baked``), and the initial disks touching the crop;
    every pass is DC-only, so the pass moves and evaluates one SH coefficient per Gaussian."""

    crop: Crop
    objects: list[int]
    jobs: tuple[CropJob, ...]  # (5,) full, front, back, slab, disks
    baked: GaussianSplatData   # the slab, colour baked (SH DC)
    own: GaussianSplatData     # the disks of the frame's objects


def plan_frame(data: GaussianSplatData, removed: np.ndarray, all_disks: GaussianSplatData, disk_normals: np.ndarray,
               own: np.ndarray, crop: Crop, objects: list[int], background: np.ndarray, config: BackgroundConfig,
               footprints: Footprints | None = None, tile: int = RasterConfig().tile_size) -> FramePlan:
    """The passes of one frame (module docstring). removed: (N,) bool over ``data``; all_disks: (D,)
    every object's initial disks, disk_normals (D, 3); own: (D,) bool, the disks of the frame's objects
    (the frame's loss covers the pixels they can reach, and the fit renders there every disk and kept
    slab Gaussian that can touch them); background: (3,) colour behind the back layer; footprints:
    ``Footprints.of(data)``, shared by the frames of a pass (made here when not given); tile: the
    renderer's tile size (``RasterConfig.tile_size``)."""
    cam, fill = crop.camera, config.fill
    footprints = footprints or Footprints.of(data)
    idx, uv, z, r = footprints.cull(cam)
    gone = removed[idx]
    kept_idx = idx[~gone]
    here = cull(all_disks, cam)
    disks_here = all_disks.subset(here)
    reach_z = DEPTH_MARGIN_SIGMAS * fill.max_disk_sigma * fill.grid + fill.grid
    front, slab, back = split_layers(data, cam, kept_idx, disks_here, disk_normals[here], fill.slab, reach_z,
                                     kept_z=z[~gone])
    slab_baked = baked(data, slab, cam)
    zeros = np.zeros(3, np.float32)
    weighed = removed_weight_subset(gone, uv, z, r, crop.size, tile)
    jobs = (CropJob(colourless(data), crop, idx[weighed], gone[weighed, None].astype(np.float32)),
            CropJob(baked(data, front, cam), crop, background=zeros),
            CropJob(baked(data, back, cam), crop, background=np.asarray(background, np.float32)),
            CropJob(slab_baked, crop, background=zeros),
            CropJob(disks_here, crop, background=zeros))
    return FramePlan(crop, objects, jobs, slab_baked, all_disks.subset(np.flatnonzero(own)))


def finish_frame(plan: FramePlan, images: list[CropImage], camera_full: Camera, config: BackgroundConfig,
                 external: tuple[np.ndarray, np.ndarray | None] | None) -> Frame:
    """The frame from its five renders (``plan.jobs`` order): region, hole, target and layers
    (module docstring). external: an editor's (target, mask) of the full image."""
    crop, fill = plan.crop, config.fill
    full, r_front, r_back, r_slab, r_disks = images
    kept = _compose_kept(r_front, r_slab, r_back)
    region, hole, mask = _region_hole_mask(full.features[..., 0], kept, r_disks, crop, config.targets)
    if external is not None:
        target_full, mask_full = external
        target = crop.sample(target_full, camera_full.width, camera_full.height).astype(np.float32)
        if mask_full is not None:
            mask = crop.sample(mask_full, camera_full.width, camera_full.height).astype(bool) & crop.inside
        source = "external"
    else:
        # the support as the exemplar's source: its slab opaque, nothing of the kept scene in front
        support = (r_slab.alpha >= SUPPORT_ALPHA) & (kept.front_trans >= SUPPORT_ALPHA) & crop.inside
        target = inpaint(kept.rgb.astype(np.float32), hole, config.targets.inpaint, config.targets.inpaint_radius,
                         support)
        source = config.targets.inpaint
    reach = disk_reach(plan.own, crop, fill.max_disk_sigma * fill.grid, fill.grid) if plan.own.num \
        else np.zeros((crop.size, crop.size), bool)
    mask = mask & reach  # elsewhere the frame is the kept render: a constant of the loss
    near = touching(plan.baked, crop, reach)
    return Frame(crop.view, crop, plan.objects, region, hole, mask.astype(np.float32), kept.rgb.astype(np.float32),
                 target.astype(np.float32), kept.front_rgb.astype(np.float32), kept.front_trans.astype(np.float32),
                 kept.back_rgb.astype(np.float32), reach, plan.baked.subset(near), source)


def render_plans(plans: list[FramePlan], crops: CropRenderer) -> list[list[CropImage] | RuntimeError]:
    """The five renders of every frame, all frames' passes in batched launches of one padded count
    (the largest pass's bucket: one program); when the renderer refuses a batch (its buffers), each
    frame is rendered alone, and a frame it still refuses gets the error."""
    pad = pass_bucket([j.num for p in plans for j in p.jobs])
    jobs = [j for p in plans for j in p.jobs]
    try:
        images = crops.render_many(jobs, pad)
        return [images[k * len(p.jobs):(k + 1) * len(p.jobs)] for k, p in enumerate(plans)]
    except RuntimeError:
        pass
    out: list[list[CropImage] | RuntimeError] = []
    for p in plans:
        try:
            out.append(crops.render_many(list(p.jobs), pass_bucket([j.num for j in p.jobs])))
        except RuntimeError as err:
            out.append(err)
    return out


def write_targets(folder: Path, frames: list[Frame], cameras: tuple[Camera, ...]) -> list[str]:
    """Full-frame target, loss mask and hole PNGs per view (the editor format; crops of one view are
    pasted into one image); returns the file names."""
    import cv2

    from phirie_jax.io.atomic import write_bytes

    written = []
    for view in sorted({f.view for f in frames}):
        cam = cameras[view]
        base = _image(cam)
        full = np.zeros((cam.height, cam.width, 3), np.float32) if base is None else base.copy()
        mask_full = np.zeros((cam.height, cam.width), np.uint8)
        hole_full = np.zeros((cam.height, cam.width), np.uint8)
        for f in (f for f in frames if f.view == view):
            rows, cols = f.crop.full_pixels()
            ok = f.crop.inside & (f.mask > 0)
            full[rows[ok], cols[ok]] = f.target[ok]
            mask_full[rows[ok], cols[ok]] = 255
            hole_full[rows[ok & f.hole], cols[ok & f.hole]] = 255
        stem = Path(cam.name).stem
        for name, img in ((f"{stem}.png", np.round(full[..., ::-1] * 255).astype(np.uint8)),
                          (f"{stem}_mask.png", mask_full), (f"{stem}_hole.png", hole_full)):
            ok_enc, buf = cv2.imencode(".png", img)
            if not ok_enc:
                raise RuntimeError(f"PNG encoding failed for {folder / name}")
            write_bytes(folder / name, buf.tobytes())
            written.append(name)
    return written
