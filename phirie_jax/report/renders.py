"""The images of ``report.html``: the capture before conversion, the converted scene after it
(from the same cameras), and a thumbnail of each object.

* before: the capture's own Gaussians (``source_gaussians``: the manifest's ``scene.gaussians``
  moved into the world frame by ``frame.capture_to_world``, as every output is);
* after: the interactive scene at t = 0 (``Environment.gaussians``: the background and every
  object placed by S_i(0), rasterized together);
* thumbnails: the square around the object cut from the "after" view that shows it largest; an
  object too small or not wholly in any view is rendered from the capture camera in which its box
  projects largest, that camera's intrinsics cropped and scaled to the square (``crop_camera``).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from kernels.gaussians import Gaussians
from phirie_jax.manifest import Manifest
from phirie_jax.types import Camera, GaussianSplatData

BOX_PERCENTILES = (1.0, 99.0)   # an object's box from its Gaussians, stray ones ignored
THUMBNAIL_MARGIN = 1.25         # the square is this much wider than the object's projected box
MIN_CUT_SIDE = 32               # px: an object this large in a view is cut from it, else rendered alone


def source_gaussians(out_dir: Path, manifest: Manifest | None = None) -> GaussianSplatData | None:
    """The capture's Gaussians in the world frame (degenerate ones dropped, as ``load_scene``
    does), read from the manifest's ``scene.gaussians``; None when that file is gone."""
    from phirie_jax.frame.resolve import world_gaussians
    from phirie_jax.io.gaussian_checks import degenerate_mask
    from phirie_jax.io.ply import read_gaussian_ply

    manifest = manifest or Manifest.load_or_create(out_dir)
    path = (manifest.get("scene") or {}).get("gaussians")
    if not path or not Path(path).is_file():
        return None
    data = read_gaussian_ply(path, allow_non_finite=True)
    data = data.subset(np.flatnonzero(~degenerate_mask(data)))
    to_world = manifest.capture_to_world()
    return data if to_world is None or np.array_equal(to_world, np.eye(4)) else world_gaussians(data, to_world)


def view_cameras(cameras: list[Camera], count: int) -> list[int]:
    """Indices of ``count`` cameras spread evenly over the capture (first and last included)."""
    if not cameras or count <= 0:
        return []
    return sorted({int(k) for k in np.linspace(0, len(cameras) - 1, min(count, len(cameras))).round()})


def box_corners(points: np.ndarray) -> np.ndarray:
    """(8, 3) corners of the axis-aligned box of ``points`` (N, 3) between ``BOX_PERCENTILES``."""
    low, high = np.percentile(points, BOX_PERCENTILES, axis=0)
    return np.array([[x, y, z] for x in (low[0], high[0]) for y in (low[1], high[1]) for z in (low[2], high[2])])


def object_square(camera: Camera, corners: np.ndarray) -> tuple[float, float, float] | None:
    """(x0, y0, side): the square, in ``camera``'s pixels, around the projection of ``corners``
    (8, 3) (× ``THUMBNAIL_MARGIN``); None when a corner is behind the camera or the square leaves
    the image."""
    uv, depth = camera.project(corners)
    if np.any(depth <= 0):
        return None
    low, high = uv.min(0), uv.max(0)
    side = THUMBNAIL_MARGIN * float(max(high - low))
    x0, y0 = 0.5 * (low + high) - 0.5 * side
    if side <= 0 or x0 < 0 or y0 < 0 or x0 + side > camera.width or y0 + side > camera.height:
        return None
    return float(x0), float(y0), side


def crop_camera(camera: Camera, corners: np.ndarray, width: int, height: int) -> tuple[Camera, float] | None:
    """A ``width`` × ``height`` camera at ``camera``'s pose whose centred square (side
    min(width, height)) is ``object_square(camera, corners)``, and that square's side in
    ``camera``'s pixels; None without a square. With s = side' / side and the square's corner
    (x0, y0): u' = s (u − x0) + (width − side') / 2 (pixel-centre coordinates kept)."""
    found = object_square(camera, corners)
    if found is None:
        return None
    x0, y0, side = found
    square = min(width, height)
    scale = square / side
    K = camera.K.copy()
    K[:2] *= scale
    K[0, 2] += 0.5 * (width - square) - scale * x0
    K[1, 2] += 0.5 * (height - square) - scale * y0
    return dataclasses.replace(camera, K=K, width=width, height=height), side


def thumbnail_camera(cameras: list[Camera], points: np.ndarray, width: int, height: int) -> Camera | None:
    """The crop (``crop_camera``) of the camera that sees ``points`` (N, 3) largest, or None."""
    corners = box_corners(points)
    crops = [crop for crop in (crop_camera(c, corners, width, height) for c in cameras) if crop is not None]
    return max(crops, key=lambda crop: crop[1])[0] if crops else None


def cut_square(image: np.ndarray, square: tuple[float, float, float], size: int) -> np.ndarray:
    """The square (x0, y0, side) of an (H, W, 3) image, resized to ``size`` × ``size`` (area filter
    when shrinking, linear when enlarging)."""
    import cv2

    x0, y0, side = square
    left, top, span = int(round(x0)), int(round(y0)), max(1, int(round(side)))
    patch = image[top:top + span, left:left + span]
    filter_ = cv2.INTER_AREA if span >= size else cv2.INTER_LINEAR
    return cv2.resize(patch, (size, size), interpolation=filter_)


def centre_square(image: np.ndarray, size: int) -> np.ndarray:
    """The centred square of an (H, W, 3) image, resized to ``size`` × ``size``."""
    height, width = image.shape[:2]
    side = min(height, width)
    return cut_square(image, ((width - side) / 2, (height - side) / 2, side), size)


@dataclasses.dataclass(frozen=True)
class ReportImages:
    """uint8 RGB images of the report (H, W, 3)."""

    cameras: list[str]                 # the views' camera names
    before: list[np.ndarray | None]    # the capture (None: its Gaussians are gone)
    after: list[np.ndarray]            # the converted scene at t = 0
    thumbnails: dict[int, np.ndarray]  # object id → square thumbnail


def _rgb8(image) -> np.ndarray:
    return np.clip(np.round(np.asarray(image) * 255.0), 0, 255).astype(np.uint8)


def render_images(out_dir: Path, views: int, width: int, thumbnail: int, background,
                  source: GaussianSplatData | None = None) -> ReportImages:
    """Render the report's images of a converted folder (module docstring). ``source``: the
    capture's Gaussians in the world frame when the caller has them (else read back).

    Every image is rendered at the views' size (a thumbnail rendered on its own is a crop camera
    of that size, its centred square cut out afterwards) and the smaller Gaussian set is padded
    with transparent Gaussians to the larger's count, so one compiled program of the renderer
    serves the page — the rollout's, when the views are at the cameras' own size."""
    import jax

    from phirie_jax.interact.environment import Environment
    from phirie_jax.render import pad_gaussians, prepared, render

    env = Environment.load(out_dir)
    scene: Gaussians = jax.tree.map(np.asarray, env.gaussians())   # padded on the host: no program per shape
    picks = [env.cameras[k] for k in view_cameras(env.cameras, views)]
    picks = [c if c.width <= width else c.scaled(width / c.width) for c in picks]
    bg = np.asarray(background, np.float32)
    source = source if source is not None else source_gaussians(out_dir)
    captured = None if source is None else source.to_host_kernel()
    means = np.asarray(scene.means)
    if captured is not None:
        size = max(captured.num, scene.num)
        captured, scene = prepared(pad_gaussians(captured, size)), pad_gaussians(scene, size)
    scene = prepared(scene)
    before = [None if captured is None else _rgb8(render(captured, c, background=bg).rgb) for c in picks]
    after = [_rgb8(render(scene, c, background=bg).rgb) for c in picks]
    offset = env.background.num
    thumbnails = {}
    size = (picks[0].width, picks[0].height) if picks else (thumbnail, thumbnail)
    for o in env.objects:
        rows = slice(offset + o.gaussians.start, offset + o.gaussians.stop)
        if rows.stop <= rows.start:
            continue
        corners = box_corners(means[rows])
        seen = [(square, image) for square, image in ((object_square(c, corners), a) for c, a in zip(picks, after))
                if square is not None and square[2] >= MIN_CUT_SIDE]
        if seen:  # cut from the view that shows it largest: no render of its own
            square, image = max(seen, key=lambda item: item[0][2])
            thumbnails[o.id] = cut_square(image, square, thumbnail)
            continue
        camera = thumbnail_camera(env.cameras, means[rows], *size)
        if camera is not None:
            thumbnails[o.id] = centre_square(_rgb8(render(scene, camera, background=bg).rgb), thumbnail)
    return ReportImages([c.name for c in picks], before, after, thumbnails)
