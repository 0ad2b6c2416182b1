"""Structure from motion with pycolmap: the pictures' cameras and a sparse point cloud.

SIFT features (``SfmConfig``'s thresholds, looser than COLMAP's: see its docstring), matched
exhaustively for photos and sequentially for a video's frames, geometrically verified, then
COLMAP's incremental mapper with a fixed seed. The model that registers the most pictures is
kept; fewer than ``min_registered`` of them is an error that says what to try. The kept model
is undistorted to PINHOLE cameras (pycolmap's undistorter, which also crops to the valid
pixels), read back with ``phirie_jax.io.colmap`` and returned as ``Camera`` records in COLMAP's
own frame (arbitrary scale and orientation: ``phirie convert`` decides up and metres).

pycolmap is an optional extra (``pip install 'phirie_jax[capture]'``); it is imported here only.
"""

from __future__ import annotations

import dataclasses
import shutil
import time
from pathlib import Path

import numpy as np

from phirie_jax.capture.config import SfmConfig
from phirie_jax.capture.frames import Frames
from phirie_jax.errors import OptionError, SceneInputError
from phirie_jax.io.colmap import read_colmap_model, read_colmap_points
from phirie_jax.progress import task
from phirie_jax.types import Camera

LOG_LEVEL_ERROR = 2   # glog's level: pycolmap's own log shows errors only (the progress display says the rest)


@dataclasses.dataclass(frozen=True)
class SfmResult:
    cameras: list[Camera]   # registered pictures, undistorted PINHOLE, sorted by name, image_path set
    points: np.ndarray      # (P, 3) float64 triangulated points
    colours: np.ndarray     # (P, 3) uint8 their colours
    images: Path            # the undistorted pictures
    sparse: Path            # the undistorted model (cameras.bin, images.bin, points3D.bin)
    record: dict            # registered/total, reprojection error, points, seconds, settings


def import_pycolmap():
    try:
        import pycolmap
    except ImportError:
        raise OptionError("phirie capture", "needs pycolmap for the structure from motion (expected it installed: "
                          "pip install 'phirie_jax[capture]', or pip install pycolmap)") from None
    pycolmap.logging.minloglevel = LOG_LEVEL_ERROR
    return pycolmap


def _options(pycolmap, config: SfmConfig):
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = config.threads
    extraction.sift.peak_threshold = config.peak_threshold
    extraction.sift.max_num_features = config.max_features
    extraction.sift.domain_size_pooling = config.domain_size_pooling
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = config.threads
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.random_seed = config.seed
    mapping.num_threads = config.threads
    mapping.min_model_size = config.min_model_size
    mapping.mapper.init_min_num_inliers = config.init_min_inliers
    mapping.mapper.init_min_tri_angle = config.init_min_tri_angle
    mapping.mapper.abs_pose_min_num_inliers = config.abs_pose_min_inliers
    mapping.mapper.abs_pose_min_inlier_ratio = config.abs_pose_min_inlier_ratio
    mapping.triangulation.ignore_two_view_tracks = not config.two_view_tracks
    return extraction, matching, mapping


def _advice(frames: Frames) -> str:
    more = ("more frames (--frames), a slower sweep" if frames.video else
            "more photos with more overlap (each part of the scene in three or more, about 10-15° apart)")
    return (f"try {more}, sharp pictures of textured surfaces, or looser settings "
            "(e.g. --config.sfm.peak-threshold 0.001 --config.sfm.init-min-inliers 20)")


def run_sfm(frames: Frames, config: SfmConfig, work: Path) -> SfmResult:
    """Cameras and points of ``frames`` (module docstring); everything is written under ``work``."""
    pycolmap = import_pycolmap()
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    database, timings = work / "database.db", {}
    extraction, matching, mapping = _options(pycolmap, config)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = config.camera_model
    mode = pycolmap.CameraMode.SINGLE if frames.one_camera else pycolmap.CameraMode.PER_IMAGE
    total = len(frames.names)

    t = time.perf_counter()
    with task(f"SIFT features of {total} pictures"):
        pycolmap.extract_features(database, frames.folder, image_names=list(frames.names), camera_mode=mode,
                                  reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
    timings["features_s"] = time.perf_counter() - t
    t = time.perf_counter()
    with task("matching them " + ("sequentially" if frames.video else "exhaustively")):
        if frames.video:
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = config.sequential_overlap
            pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing,
                                      device=pycolmap.Device.cpu)
        else:
            pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
    timings["matching_s"] = time.perf_counter() - t
    t = time.perf_counter()
    with task("incremental mapping"):
        models = pycolmap.incremental_mapping(database, frames.folder, work / "models", mapping)
    timings["mapping_s"] = time.perf_counter() - t
    best = max(models.values(), key=lambda r: r.num_reg_images(), default=None)
    registered = 0 if best is None else best.num_reg_images()
    if registered < config.min_registered * total:
        raise SceneInputError(frames.record.get("source"), "structure from motion",
                              f"{registered} of {total} pictures registered in {len(models)} model(s) "
                              f"({100 * registered / total:.0f} %, expected at least "
                              f"{100 * config.min_registered:.0f} %): {_advice(frames)}")
    names = {best.image(i).name for i in best.reg_image_ids()}
    reprojection = float(best.compute_mean_reprojection_error())
    model = work / "model"
    model.mkdir()
    best.write(model)

    t = time.perf_counter()
    undistorted = work / "undistorted"
    with task("undistorting to pinhole cameras"):
        pycolmap.undistort_images(undistorted, model, frames.folder, output_type="COLMAP")
    timings["undistort_s"] = time.perf_counter() - t
    sparse = undistorted / "sparse"
    cameras, _ = read_colmap_model(sparse, image_dir=undistorted / "images", scene_root=undistorted)
    points = read_colmap_points(sparse)
    record = {"pictures": total, "registered": registered, "registered_fraction": round(registered / total, 4),
              "unregistered": sorted(set(frames.names) - names), "models": len(models),
              "mean_reprojection_error_px": round(reprojection, 4), "points": int(best.num_points3D()),
              "matching": "sequential" if frames.video else "exhaustive",
              "camera_model": config.camera_model, "cameras": "single" if frames.one_camera else "per picture",
              "undistorted_size": sorted({(c.width, c.height) for c in cameras}),
              **{k: round(v, 3) for k, v in timings.items()}, "config": dataclasses.asdict(config)}
    return SfmResult(cameras, points.xyz, points.rgb, undistorted / "images", sparse, record)


def load_sfm(work: Path, record: dict) -> SfmResult:
    """The result ``run_sfm`` left in ``work`` (to resume a capture)."""
    undistorted = work / "undistorted"
    cameras, _ = read_colmap_model(undistorted / "sparse", image_dir=undistorted / "images", scene_root=undistorted)
    points = read_colmap_points(undistorted / "sparse")
    return SfmResult(cameras, points.xyz, points.rgb, undistorted / "images", undistorted / "sparse", record)
