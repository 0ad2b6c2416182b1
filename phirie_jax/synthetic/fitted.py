"""Fitted synthetic scenes: the capture's Gaussians obtained the way users obtain them.

``phirie synth OUT --fitted`` keeps everything a synthetic scene folder holds (meshes, images,
cameras, masks, gt/) but replaces its ideal, surface-aligned Gaussians with a 3DGS optimization
of the rendered training images (Kerbl et al. 2023, shortened):

- random initialization: points drawn uniformly in a box around the point the cameras look at,
  kept where at least ``min_init_views`` cameras see them; colour = the mean of the pixels they
  project to; isotropic scale = mean distance to the 3 nearest points; opacity 0.1. Nothing is
  taken from the true Gaussians.
- Adam on every parameter, one training view per step (an epoch visits every view once, in a
  seeded order), loss 0.8·L1 + 0.2·(1 − SSIM) (``kernels.splat_fit``), the position learning rate
  decaying exponentially, SH bands switched on one at a time every ``sh_band_interval`` steps.
- every ``densify_interval`` steps between ``densify_start`` and ``densify_stop`` (fractions of the steps): Gaussians whose mean
  view-space positional gradient exceeds ``grad_threshold`` are cloned (small) or split in two
  (larger than ``percent_dense`` × the scene extent), within ``max_gaussians``; then those almost
  transparent or larger than ``max_scale`` × the extent are pruned.
- Gaussian arrays are padded to power-of-two buckets (``phirie_jax.render.gaussian_bucket``) and
  the intersection capacity grows by powers of two, so a fit compiles a handful of programs.

The loop and the densification are those of ``phirie capture`` (``phirie_jax.capture.train``,
``phirie_jax.capture.densify``), run with this schedule (``FitConfig.training``): no opacity
reset, large Gaussians pruned from the start, the screen gradient recovered from the world one.

Everything is seeded: the same images, cameras, config and seed give the same Gaussians (on one
backend). The folder then records how it was fitted in ``gt/fit.json`` and in the PLY's header
comments; the ideal capture is kept as ``gt/ideal/point_cloud.ply`` (with its labels), and
``gt/labels.npy`` labels the fitted Gaussians by the nearest ideal Gaussian (``LABEL_RADIUS``).
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from kernels.sh import num_sh_coeffs, rgb_to_sh_dc
from phirie_jax.capture.config import TrainConfig
from phirie_jax.capture.densify import densify_and_prune  # noqa: F401  (the fit's densification, re-exported)
from phirie_jax.capture.train import Views, fraction_step, train_gaussians, views_psnr
from phirie_jax.geometry import sigmoid
from phirie_jax.io.atomic import write_bytes, write_text
from phirie_jax.io.ply import read_gaussian_ply, write_gaussian_ply
from phirie_jax.types import Camera, GaussianSplatData

LABEL_RADIUS = 0.02       # m: a fitted Gaussian takes the label of the nearest ideal one this close, else 0
INIT_OPACITY = 0.1        # 3DGS's initial opacity
EXTENT_MARGIN = 1.1       # scene extent = this × the largest camera distance from the scene centre (3DGS)
INIT_OVERSAMPLE = 8       # candidate points drawn per kept one, at most, by the rejection sampling


@dataclasses.dataclass(frozen=True)
class FitConfig:
    """How the capture's Gaussians are fitted. Rates are per Adam step; positions in metres.

    The schedule is 3DGS's compressed about 100× (it trains 30K steps, densifies every 100 from
    500 to 15K, adds an SH band every 1K), with faster rates: the ``tiny`` preset reaches a train
    PSNR of about 34 dB in under two minutes on two shared CPU cores (19 s compiling, 86 s running:
    ``experiments/results/fit_bench_cpu.json``). Larger presets want more steps (``--fit-steps``).
    """

    steps: int = 300                 # Adam steps, one training view each
    initial_points: int = 4096       # random initialization
    min_init_views: int = 2          # a random point is kept where this many cameras see it
    max_gaussians: int = 32768       # densification stops adding at this count
    sh_degree: int = 3
    sh_band_interval: int = 50       # steps between switching on SH bands 1, 2, 3
    lr_position: float = 1.6e-3      # × scene extent, at the first step ...
    lr_position_final: float = 1.6e-5  # ... decaying exponentially to this at the last
    lr_colour: float = 0.01          # SH DC; the higher bands get 1/20 of it (3DGS)
    lr_opacity: float = 0.05
    lr_scale: float = 0.01
    lr_rotation: float = 0.005
    dssim_weight: float = 0.2        # loss = (1 − λ) L1 + λ (1 − SSIM)
    densify_start: float = 1 / 6     # densify from this fraction of the steps ...
    densify_stop: float = 3 / 4      # ... until this one: the last quarter lets the set settle
    densify_interval: int = 25       # steps
    grad_threshold: float = 2e-4     # mean view-space positional gradient (NDC units, as 3DGS)
    percent_dense: float = 0.01      # × extent: larger Gaussians are split, smaller ones cloned
    min_opacity: float = 0.005       # pruned below
    max_scale: float = 0.1           # × extent: pruned above (largest axis)

    def training(self) -> TrainConfig:
        """This fit as the shared training loop's schedule (``phirie_jax.capture.train``)."""
        return TrainConfig(
            steps=self.steps, max_gaussians=self.max_gaussians, sh_degree=self.sh_degree,
            sh_band_interval=self.sh_band_interval, lr_position=self.lr_position,
            lr_position_final=self.lr_position_final, lr_colour=self.lr_colour, lr_opacity=self.lr_opacity,
            lr_scale=self.lr_scale, lr_rotation=self.lr_rotation, dssim_weight=self.dssim_weight,
            densify_from=fraction_step(self.densify_start, self.steps),
            densify_until=fraction_step(self.densify_stop, self.steps), densify_interval=self.densify_interval,
            opacity_reset_interval=0, grad_threshold=self.grad_threshold, percent_dense=self.percent_dense,
            min_opacity=self.min_opacity, max_scale=self.max_scale, exact_screen_gradient=False,
            init_opacity=INIT_OPACITY, checkpoint_interval=0, holdout_every=0)


# Each synthetic preset's fit: about 100 Adam steps per training view, the SH bands and the
# densification on the same fractions of the schedule, room for the Gaussian counts a trainer
# reaches at that image size. ``tiny`` is the class default (tests); ``default`` is fitted on a GPU
# (``experiments/fit_scenes.py``) and its result reproduced by its seed.
FIT_PRESETS = {
    "tiny": FitConfig(),
    "default": FitConfig(steps=3600, initial_points=16384, max_gaussians=65536, sh_band_interval=300,
                         densify_interval=50),
    "large": FitConfig(steps=6000, initial_points=65536, max_gaussians=524288, sh_band_interval=500,
                       densify_interval=100),
    # ~100 steps per view, as the default preset's fit
    "crowded": FitConfig(steps=4800, initial_points=32768, max_gaussians=262144, sh_band_interval=400,
                         densify_interval=50),
}


def fit_config_for(preset: str, steps: int | None = None) -> FitConfig:
    """The fit of a synthetic preset (``FIT_PRESETS``), with ``steps`` Adam steps if given."""
    if preset not in FIT_PRESETS:
        raise ValueError(f"no fit for preset {preset!r} (expected one of {sorted(FIT_PRESETS)})")
    config = FIT_PRESETS[preset]
    return config if steps is None else dataclasses.replace(config, steps=steps)


@dataclasses.dataclass(frozen=True)
class FitResult:
    gaussians: GaussianSplatData  # the fitted set (SH degree ``config.sh_degree``)
    record: dict                  # steps, Gaussian counts, train PSNR, first/last loss, densification, times


def scene_region(cameras: list[Camera]) -> tuple[np.ndarray, float]:
    """The point closest (least squares) to every optical axis, and the scene extent: 1.1 × the
    largest camera distance from it."""
    centres, axes = [], []
    for cam in cameras:
        rot, trans = cam.world_to_camera[:3, :3], cam.world_to_camera[:3, 3]
        centres.append(-rot.T @ trans)
        axes.append(rot[2])
    centres, axes = np.asarray(centres), np.asarray(axes)
    proj = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]   # (V, 3, 3) orthogonal to each axis
    centre = np.linalg.solve(proj.sum(0), np.einsum("vij,vj->i", proj, centres))
    return centre, EXTENT_MARGIN * float(np.max(np.linalg.norm(centres - centre, axis=1)))


def _project(points: np.ndarray, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Pixel indices (P, 2) (column, row) and whether each point is in front and inside the image."""
    p = points @ cam.world_to_camera[:3, :3].T + cam.world_to_camera[:3, 3]
    z = p[:, 2]
    uv = (p @ np.asarray(cam.K).T)[:, :2] / np.where(z > 1e-6, z, 1.0)[:, None]
    ij = np.floor(uv).astype(np.int64)
    inside = (z > 1e-6) & (ij[:, 0] >= 0) & (ij[:, 0] < cam.width) & (ij[:, 1] >= 0) & (ij[:, 1] < cam.height)
    return ij, inside


def random_init(images: list[np.ndarray], cameras: list[Camera], config: FitConfig, rng) -> GaussianSplatData:
    """``config.initial_points`` random Gaussians in the cameras' common view (module docstring)."""
    from scipy.spatial import cKDTree

    centre, extent = scene_region(cameras)
    half = extent / EXTENT_MARGIN
    points = rng.uniform(centre - half, centre + half, size=(INIT_OVERSAMPLE * config.initial_points, 3))
    colour_sum = np.zeros_like(points)
    views = np.zeros(len(points), np.int64)
    for image, cam in zip(images, cameras):
        ij, inside = _project(points, cam)
        colour_sum[inside] += image[ij[inside, 1], ij[inside, 0]]
        views += inside
    keep = np.flatnonzero(views >= config.min_init_views)[: config.initial_points]
    if len(keep) < 4:
        raise ValueError(f"only {len(keep)} random points are seen by {config.min_init_views} cameras: "
                         "do the cameras look at a common region?")
    means = points[keep]
    colours = colour_sum[keep] / views[keep, None]
    dist, _ = cKDTree(means).query(means, k=4)  # itself + 3 neighbours
    scale = np.maximum(dist[:, 1:].mean(axis=1), 1e-4)
    n, k = len(means), num_sh_coeffs(config.sh_degree)
    sh = np.zeros((n, k, 3), np.float32)
    sh[:, 0] = rgb_to_sh_dc(colours)
    return GaussianSplatData(
        means=means.astype(np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        log_scales=np.repeat(np.log(scale)[:, None], 3, axis=1).astype(np.float32),
        opacity_logits=np.full(n, np.log(INIT_OPACITY / (1 - INIT_OPACITY)), np.float32), sh=sh)


def fit_gaussians(images: list[np.ndarray], cameras: list[Camera], config: FitConfig = FitConfig(), seed: int = 0,
                  background=(0.0, 0.0, 0.0)) -> FitResult:
    """Fit 3DGS to the training views. images: V arrays (H, W, 3) in [0, 1], one size; cameras: V
    pinhole cameras of that size; background: the colour the images show where nothing is."""
    if len({(c.width, c.height) for c in cameras}) != 1:
        raise ValueError("fit_gaussians: every training view must have the same size")
    rng = np.random.default_rng(seed)
    _, extent = scene_region(cameras)
    data = random_init(images, cameras, config, rng)
    views = Views.of([np.asarray(im, np.float32) for im in images], cameras)
    trained = train_gaussians(data, views, extent, config.training(), rng, background)
    fitted = trained.gaussians.subset(sigmoid(trained.gaussians.opacity_logits) >= config.min_opacity)
    psnrs = views_psnr(fitted, views, background, trained.raster)
    t = trained.record
    record = {"steps": config.steps, "seed": seed, "gaussians": fitted.num, "initial_gaussians": data.num,
              "train_psnr": round(float(np.mean(psnrs)), 3), "train_psnr_per_view": np.round(psnrs, 3).tolist(),
              **{k: t[k] for k in ("loss_first", "loss_last", "densify", "buckets", "capacity", "capacity_retries",
                                   "programs", "backend", "device", "wall_s", "step_s_median", "compile_s", "run_s")},
              "config": dataclasses.asdict(config)}
    return FitResult(fitted, record)


def read_training_views(scene_dir: Path) -> tuple[list[np.ndarray], list[Camera]]:
    """The folder's cameras and their images as floats in [0, 1] (what a user's trainer reads)."""
    import cv2

    from phirie_jax.io.scene import load_scene

    cameras = list(load_scene(scene_dir).require_cameras())
    images = []
    for cam in cameras:
        bgr = cv2.imread(str(cam.image_path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"{cam.image_path}: cannot read the training image")
        images.append(bgr[..., ::-1].astype(np.float32) / 255.0)
    return images, cameras


def fit_scene_folder(scene_dir: str | Path, background, config: FitConfig = FitConfig(), seed: int = 0
                     ) -> FitResult:
    """Replace a synthesized folder's ideal Gaussians with fitted ones (module docstring)."""
    scene_dir = Path(scene_dir)
    if (scene_dir / "gt" / "fit.json").exists():
        raise ValueError(f"{scene_dir}: its Gaussians are already fitted (gt/fit.json)")
    images, cameras = read_training_views(scene_dir)
    result = fit_gaussians(images, cameras, config, seed, background)
    install_fit(scene_dir, result)
    return result


def install_fit(scene_dir: str | Path, result: FitResult) -> None:
    """Make a synthesized folder's capture the fitted set: the ideal Gaussians and labels move to
    gt/ideal/, the fitted ones are labelled by the nearest ideal Gaussian, gt/fit.json records the
    fit. Also for a fit made elsewhere (a GPU host) of the same preset and seed."""
    from scipy.spatial import cKDTree

    scene_dir = Path(scene_dir)
    if (scene_dir / "gt" / "fit.json").exists():
        raise ValueError(f"{scene_dir}: its Gaussians are already fitted (gt/fit.json)")
    ideal = read_gaussian_ply(scene_dir / "point_cloud.ply")
    ideal_labels = np.load(scene_dir / "gt" / "labels.npy")
    write_gaussian_ply(scene_dir / "gt" / "ideal" / "point_cloud.ply", ideal)
    _write_npy(scene_dir / "gt" / "ideal" / "labels.npy", ideal_labels)
    dist, nearest = cKDTree(ideal.means).query(result.gaussians.means)
    _write_npy(scene_dir / "gt" / "labels.npy",
               np.where(dist <= LABEL_RADIUS, ideal_labels[nearest], 0).astype(ideal_labels.dtype))
    r = result.record
    comment = (f"comment phirie fitted: {r['steps']} steps, seed {r['seed']}, {r['gaussians']} Gaussians, "
               f"train PSNR {r['train_psnr']:.2f} dB (gt/fit.json)")
    write_gaussian_ply(scene_dir / "point_cloud.ply", dataclasses.replace(result.gaussians, comments=(comment,)))
    write_text(scene_dir / "gt" / "fit.json", json.dumps(r, indent=2))


def _write_npy(path: Path, array: np.ndarray) -> None:
    import io

    buf = io.BytesIO()
    np.save(buf, array)
    write_bytes(path, buf.getvalue())



def synthesize_fitted(out_dir: str | Path, preset: str = "default", seed: int = 0,
                      config: FitConfig | None = None) -> tuple:
    """``synthesize`` then ``fit_scene_folder`` (the fit seeded with the scene's seed; ``config``
    defaults to the preset's, ``FIT_PRESETS``). Returns (the ``SyntheticScene``, the ``FitResult``)."""
    from phirie_jax.synthetic.scene import PRESETS, synthesize

    config = fit_config_for(preset) if config is None else config
    scene = synthesize(out_dir, preset=preset, seed=seed)
    return scene, fit_scene_folder(out_dir, PRESETS[preset].background_rgb, config, seed=seed)


def ensure_synthesized(path: str | Path, preset: str, seed: int, fitted: bool = False,
                       config: FitConfig | None = None) -> Path:
    """A synthesized (``fitted``: and fitted, by ``config`` or the preset's fit) folder at
    ``path``, made unless it is complete (gt/objects.json, and gt/fit.json when fitted). For the
    evaluations in ``experiments/``."""
    path = Path(path)
    config = fit_config_for(preset) if config is None else config
    if not (path / "gt" / "objects.json").exists() or (fitted and not (path / "gt" / "fit.json").exists()):
        from phirie_jax.synthetic.scene import synthesize

        t0 = time.perf_counter()
        if fitted:
            _, result = synthesize_fitted(path, preset, seed, config)
            print(f"synthesized and fitted {path} in {time.perf_counter() - t0:.1f} s "
                  f"(train PSNR {result.record['train_psnr']:.2f} dB)", flush=True)
        else:
            synthesize(path, preset, seed)
            print(f"synthesized {path} in {time.perf_counter() - t0:.1f} s", flush=True)
    return path
