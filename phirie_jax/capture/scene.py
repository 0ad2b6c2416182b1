"""The scene folder a capture writes, nerfstudio's layout, which ``phirie convert`` reads as it is:

    transforms.json     the registered pictures' cameras (OpenGL camera-to-world, PINHOLE)
    images/NAME.png     the undistorted pictures the Gaussians were trained on
    sparse/0/*.bin      the same cameras and the SfM points as a COLMAP model
    point_cloud.ply     the trained Gaussians (INRIA PLY, SH degree 3), opacity ≥ min_opacity
    capture.json        what was done: pictures, SfM statistics, training statistics, held-out PSNR

Also here: the training views (every picture at one size) and the held-out split.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from collections import Counter
from pathlib import Path

import numpy as np

from phirie_jax.errors import SceneInputError
from phirie_jax.io.atomic import write_bytes, write_text
from phirie_jax.io.colmap import write_colmap_binary
from phirie_jax.io.ply import write_gaussian_ply
from phirie_jax.io.transforms_json import write_transforms_json
from phirie_jax.types import Camera, GaussianSplatData

CAPTURE_RECORD = "capture.json"   # written by phirie capture only: marks its output folders
SCHEMA = "phirie/capture/1"


def held_out(count: int, every: int) -> np.ndarray:
    """(count,) bool: every ``every``-th view, starting with the first, is held out (gsplat's
    ``test_every``); none when ``every`` is 0."""
    index = np.arange(count)
    return (index % every == 0) if every else np.zeros(count, bool)


def training_views(cameras: list[Camera]) -> tuple[list[Camera], list[np.ndarray]]:
    """The cameras and their pictures (H, W, 3) uint8 RGB at one size: pictures of another size
    than the most common one (an undistorter crops each camera's valid region) are resized to it,
    their intrinsics scaled per axis."""
    import cv2

    width, height = Counter((c.width, c.height) for c in cameras).most_common(1)[0][0]
    out_cameras, images = [], []
    for cam in cameras:
        bgr = cv2.imread(str(cam.image_path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise SceneInputError(cam.image_path, None, "cannot read the undistorted picture")
        if (cam.width, cam.height) != (width, height):
            sx, sy = width / cam.width, height / cam.height
            bgr = cv2.resize(bgr, (width, height), interpolation=cv2.INTER_AREA)
            K = cam.K.copy()
            K[0] *= sx
            K[1] *= sy
            cam = dataclasses.replace(cam, K=K, width=width, height=height, image_path=None)
        out_cameras.append(cam)
        images.append(np.ascontiguousarray(bgr[..., ::-1]))
    return out_cameras, images


def write_scene(stage: Path, cameras: list[Camera], images: list[np.ndarray], points: np.ndarray,
                colours: np.ndarray, gaussians: GaussianSplatData) -> None:
    """The scene folder (module docstring) but ``capture.json`` written into ``stage`` (a new folder)."""
    import cv2

    (stage / "images").mkdir(parents=True)
    for cam, image in zip(cameras, images):
        if cam.image_path is not None and cam.image_path.suffix.lower() == ".png":  # the picture as trained on
            shutil.copyfile(cam.image_path, stage / "images" / cam.name)
        else:
            ok, buf = cv2.imencode(".png", image[..., ::-1])
            if not ok:
                raise RuntimeError(f"PNG encoding failed for {cam.name}")
            write_bytes(stage / "images" / cam.name, buf.tobytes())
    written = [dataclasses.replace(c, image_path=stage / "images" / c.name) for c in cameras]
    write_transforms_json(stage / "transforms.json", written)
    write_colmap_binary(stage / "sparse" / "0", written, points, colours)
    write_gaussian_ply(stage / "point_cloud.ply", gaussians)


def write_record(stage: Path, record: dict) -> None:
    """``capture.json``: the capture's record (``run_capture``'s), with its schema."""
    write_text(stage / CAPTURE_RECORD, json.dumps({"schema": SCHEMA, **record}, indent=2) + "\n")
