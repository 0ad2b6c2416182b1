"""Settings of ``phirie capture``: the frames, the structure from motion and the 3DGS training.

Every number has the value it has in the tool it comes from (COLMAP, gsplat 1.5.3's
``simple_trainer`` with ``DefaultStrategy``), except where a comment says why it differs. The
module imports nothing heavy, so the command line can build these without starting JAX.
"""

from __future__ import annotations

import dataclasses

from phirie_jax.ranges import (
    AT_LEAST_ONE,
    FRACTION,
    NON_NEGATIVE,
    OPEN_FRACTION,
    POSITIVE,
    POSITIVE_FRACTION,
    Each,
    Range,
    check_ranges,
)

VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm", ".mts")
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp")


@dataclasses.dataclass(frozen=True)
class FramesConfig:
    """Which pictures the capture is made of.

    Attributes:
        frames: for a video, this many frames spread over it, each the sharpest (variance of the
            Laplacian) of its stretch of the video.
        resolution: pictures whose longer side has more pixels are downscaled to it before
            anything else (INRIA's 3DGS downscales past 1.6K for the same reason: memory and time).
        min_images: fewer usable pictures than this is an error.
    """

    frames: int = 120
    resolution: int = 1600
    min_images: int = 5

    def __post_init__(self):
        check_ranges(self, {"frames": Range(2), "resolution": Range(32), "min_images": Range(2)})


# COLMAP 4's own values of the fields ``SfmConfig`` loosens (for comparison: experiments/capture_sfm.py)
COLMAP_DEFAULTS = {"peak_threshold": 0.02 / 3, "domain_size_pooling": False, "init_min_inliers": 100,
                   "init_min_tri_angle": 16.0, "abs_pose_min_inliers": 30, "abs_pose_min_inlier_ratio": 0.25,
                   "two_view_tracks": False, "min_model_size": 10}


@dataclasses.dataclass(frozen=True)
class SfmConfig:
    """Structure from motion with pycolmap (SIFT, matching, incremental mapping, undistortion).

    COLMAP's defaults are tuned for large, sharp photo collections; on a hand-held set of a few
    dozen pictures they often register a handful: a 12-view synthetic arc registered 2 of 12 with
    them and 12 of 12 with these (``experiments/results/capture_sfm.json`` has the real captures).
    What is looser than COLMAP, and why:

    Attributes:
        peak_threshold: SIFT's detection threshold (COLMAP 0.0067): a third of it finds 2–3× the
            keypoints in the soft, low-contrast regions of phone pictures and renders.
        max_features: SIFT keypoints kept per picture (COLMAP's 8192).
        domain_size_pooling: DSP-SIFT descriptors (pooled over scales; COLMAP's option, off by
            default there): on the 12-view arc the focal length came out 4 % short without them
            (rotations off by up to 1.2°) and within 0.2 % with them (0.6°), for 2-3× the
            extraction time.
        init_min_inliers: inlier matches of the pair the model starts from (COLMAP 100).
        init_min_tri_angle: degrees of parallax of that pair (COLMAP 16: an orbit with 10° steps
            has no such pair among neighbours).
        abs_pose_min_inliers: matches to register one more picture (COLMAP 30).
        abs_pose_min_inlier_ratio: their inlier fraction (COLMAP 0.25).
        two_view_tracks: keep points seen in two pictures only (COLMAP drops them: few pictures
            mean many such points, and the next picture registers on them).
        min_model_size: pictures in a model that is kept (COLMAP 10).
        min_registered: the fraction of pictures that must register, else the capture stops
            with an error saying what to try.
        sequential_overlap: for a video, each frame is matched with this many that follow
            (COLMAP's sequential matcher); photos are matched exhaustively.
        camera_model: COLMAP's model for the pictures before undistortion (SIMPLE_RADIAL: one
            focal length and one radial coefficient, COLMAP's default).
        seed: the mapper's random seed (a fixed seed gives the same model on the same machine).
        threads: CPU threads for SIFT, matching and mapping (-1: all).
    """

    peak_threshold: float = 0.002
    max_features: int = 8192
    domain_size_pooling: bool = True
    init_min_inliers: int = 30
    init_min_tri_angle: float = 4.0
    abs_pose_min_inliers: int = 12
    abs_pose_min_inlier_ratio: float = 0.1
    two_view_tracks: bool = True
    min_model_size: int = 3
    min_registered: float = 0.6
    sequential_overlap: int = 10
    camera_model: str = "SIMPLE_RADIAL"
    seed: int = 0
    threads: int = -1

    def __post_init__(self):
        check_ranges(self, {"peak_threshold": POSITIVE, "max_features": Range(64), "init_min_inliers": Range(8),
                            "init_min_tri_angle": Range(0, 90, low_open=True), "abs_pose_min_inliers": Range(4),
                            "abs_pose_min_inlier_ratio": OPEN_FRACTION, "min_model_size": Range(2),
                            "min_registered": POSITIVE_FRACTION, "sequential_overlap": AT_LEAST_ONE,
                            "seed": NON_NEGATIVE, "threads": Range(-1)})


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """3DGS training (Kerbl et al. 2023) as gsplat 1.5.3's ``simple_trainer`` runs it by default.

    One training view per step (an epoch visits every view once, in a seeded order); loss
    (1 − λ) L1 + λ (1 − SSIM); Adam (eps 1e-15) with a learning rate per parameter, the position's
    decaying exponentially; SH bands switched on one at a time; ``DefaultStrategy``'s
    densification: after every ``densify_interval`` steps from ``densify_from`` until
    ``densify_until``, Gaussians whose mean screen-space gradient (NDC units) exceeds
    ``grad_threshold`` are cloned (largest axis ≤ ``percent_dense`` × the scene scale) or split
    in two (larger), within ``max_gaussians``; those below ``min_opacity`` are pruned, and after the
    first opacity reset also those larger than ``max_scale`` × the scene scale. Every
    ``opacity_reset_interval`` steps the opacities are clamped to 2 × ``min_opacity`` and their
    Adam moments zeroed. The scene scale is 1.1 × the largest distance of a camera from the
    cameras' mean (gsplat's).

    Attributes:
        steps: Adam steps.
        max_gaussians: densification stops adding at this count (gsplat has no limit).
        sh_degree: the highest SH band.
        sh_band_interval: steps between switching on SH bands 1, 2, 3.
        lr_position: × the scene scale, at the first step ...
        lr_position_final: ... decaying exponentially to this at the last (gsplat: 1/100 of it).
        lr_colour: SH DC (gsplat's sh0); the higher bands get 1/20 of it (shN).
        lr_opacity: opacity logits.
        lr_scale: log scales.
        lr_rotation: quaternions.
        dssim_weight: λ of the loss.
        densify_from: steps before the first densification.
        densify_until: no densification (nor opacity reset) from this step on.
        densify_interval: steps between densifications.
        opacity_reset_interval: steps between opacity resets (0: never). gsplat 1.5.3 means
            to reset every 3000 steps but never does (``step % reset_every == 0 & step > 0``
            parses as a chained comparison that is always false; fixed after 1.5.3).
        grad_threshold: mean screen-space positional gradient (NDC units) that densifies.
        percent_dense: × the scene scale: larger Gaussians are split, smaller ones cloned.
        min_opacity: pruned below.
        max_scale: × the scene scale: pruned above (largest axis), after the first reset.
        exact_screen_gradient: densify on the gradient at the projected mean (gsplat's), not
            on its approximation from the world-space gradient (``kernels.splat_fit``).
        init_opacity: opacity of the Gaussians made from the SfM points.
        checkpoint_interval: steps between checkpoints (0: none), for ``--resume``.
        holdout_every: every this-th picture (in name order, starting with the first) is
            held out of training and scored (gsplat's ``test_every``); 0: train on all.
        seed: the training's random seed (view order, split offsets, initial rotations).
        background: the colour behind every Gaussian, RGB in [0, 1] (gsplat's: black). Pictures
            against a plain backdrop (a studio wall, a synthetic render) train faster given its
            colour: SfM finds no points on a featureless backdrop to start Gaussians there.
    """

    steps: int = 7000
    max_gaussians: int = 2_000_000
    sh_degree: int = 3
    sh_band_interval: int = 1000
    lr_position: float = 1.6e-4
    lr_position_final: float = 1.6e-6
    lr_colour: float = 2.5e-3
    lr_opacity: float = 5e-2
    lr_scale: float = 5e-3
    lr_rotation: float = 1e-3
    dssim_weight: float = 0.2
    densify_from: int = 500
    densify_until: int = 15000
    densify_interval: int = 100
    opacity_reset_interval: int = 3000
    grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    min_opacity: float = 0.005
    max_scale: float = 0.1
    exact_screen_gradient: bool = True
    init_opacity: float = 0.1
    checkpoint_interval: int = 1000
    holdout_every: int = 8
    seed: int = 0
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self):
        check_ranges(self, {
            "steps": AT_LEAST_ONE, "max_gaussians": AT_LEAST_ONE, "sh_degree": Range(0, 3),
            "sh_band_interval": AT_LEAST_ONE, "lr_position": POSITIVE, "lr_position_final": POSITIVE,
            "lr_colour": NON_NEGATIVE, "lr_opacity": NON_NEGATIVE, "lr_scale": NON_NEGATIVE,
            "lr_rotation": NON_NEGATIVE, "dssim_weight": Range(0, 1), "densify_from": NON_NEGATIVE,
            "densify_until": NON_NEGATIVE, "densify_interval": AT_LEAST_ONE,
            "opacity_reset_interval": NON_NEGATIVE, "grad_threshold": POSITIVE, "percent_dense": POSITIVE,
            "min_opacity": OPEN_FRACTION, "max_scale": POSITIVE, "init_opacity": OPEN_FRACTION,
            "checkpoint_interval": NON_NEGATIVE, "holdout_every": NON_NEGATIVE, "seed": NON_NEGATIVE,
            "background": Each(FRACTION, count=3)})


@dataclasses.dataclass(frozen=True)
class CaptureConfig:
    """Everything ``phirie capture`` does, stage by stage."""

    frames: FramesConfig = FramesConfig()
    sfm: SfmConfig = SfmConfig()
    train: TrainConfig = TrainConfig()
