"""What a synthetic scene looks like with its objects gone: the reference for scoring the
background stage (``experiments/background_eval.py``, the demo's summary)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from phirie_jax.io.ply import read_gaussian_ply
from phirie_jax.types import GaussianSplatData

SAME_GAUSSIAN = 1e-6  # m: a capture Gaussian is a ground-truth one when their centres are this close
REGION_WEIGHT = 0.01  # a pixel is uncovered where the capture's object Gaussians carried this much weight


@dataclasses.dataclass(frozen=True)
class BackgroundTruth:
    capture: GaussianSplatData  # the capture as written (point_cloud.ply)
    labels: np.ndarray          # (N,) ground-truth object id of each capture Gaussian, 0 = background
    truth: GaussianSplatData    # gt/background.ply ∪ the capture's floaters: the scene without objects
    hidden: np.ndarray          # (M,) bool per truth Gaussian: tabletop that no capture Gaussian had


def background_truth(scene_dir: str | Path) -> BackgroundTruth:
    """The truth of a ``phirie synth`` folder (it needs ``gt/background.ply`` and ``gt/labels.npy``).

    In a fitted folder (``phirie synth --fitted``) the floaters and the hidden tabletop are those of
    the ideal capture (``gt/ideal/``): the truth is the scene's, whatever Gaussians were fitted."""
    from scipy.spatial import cKDTree


    scene_dir = Path(scene_dir)
    capture = read_gaussian_ply(scene_dir / "point_cloud.ply")
    labels = np.load(scene_dir / "gt" / "labels.npy")
    background = read_gaussian_ply(scene_dir / "gt" / "background.ply")
    ideal, ideal_labels = capture, labels
    if (scene_dir / "gt" / "ideal" / "point_cloud.ply").exists():
        ideal = read_gaussian_ply(scene_dir / "gt" / "ideal" / "point_cloud.ply")
        ideal_labels = np.load(scene_dir / "gt" / "ideal" / "labels.npy")
    d, _ = cKDTree(background.means).query(ideal.means[ideal_labels == 0])
    floaters = ideal.subset(np.flatnonzero(ideal_labels == 0)[d > SAME_GAUSSIAN])
    d_hidden, _ = cKDTree(ideal.means).query(background.means)
    hidden = np.concatenate([d_hidden > SAME_GAUSSIAN, np.zeros(floaters.num, bool)])
    return BackgroundTruth(capture, labels, GaussianSplatData.join([background, floaters], like=background), hidden)


def uncovered_region(truth: BackgroundTruth, camera, background_rgb, weight: float = REGION_WEIGHT) -> np.ndarray:
    """(H, W) bool: where the capture's object Gaussians carry at least ``weight`` in ``camera``."""
    import jax.numpy as jnp

    from phirie_jax.render import render

    objects = jnp.asarray((truth.labels > 0)[:, None], jnp.float32)
    out = render(truth.capture.to_kernel(), camera, background=np.asarray(background_rgb, np.float32),
                 features=objects)
    return np.asarray(out.features)[..., 0] >= weight
