"""Optimiser artefacts added to a synthetic capture: what gsplat's densification leaves behind.

``add_artefacts(scene_dir, seed, bumps, floaters)`` adds to a synthesized folder's capture
(``point_cloud.ply``; ``gt/labels.npy`` gets label 0 for every added Gaussian, none is an object):

- floor bumps: low domes of opaque, table-coloured Gaussians on the tabletop, 1–2 cm tall and
  2.5–4 cm in radius, away from the objects (a trained model's bumpy, lumpy table);
- floaters: small clouds of semi-transparent blobs 5–30 cm over the tabletop.

``gt/artefacts.json`` lists them (kind, centre, radius, height) so an evaluation can tell a phantom
on a bump from one elsewhere. Everything is seeded.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from phirie_jax.io.atomic import write_bytes, write_text
from phirie_jax.io.ply import read_gaussian_ply, write_gaussian_ply
from phirie_jax.types import GaussianSplatData

BUMP_RADIUS = (0.025, 0.04)     # m
BUMP_HEIGHT = (0.01, 0.02)      # m: what a 3 cm object-height rule must not take for an object
BUMP_SPACING = 0.004            # m between the bump's Gaussians
FLOATER_HEIGHT = (0.05, 0.3)    # m over the tabletop
FLOATER_BLOBS = 12              # Gaussians per floater cloud
OBJECT_CLEARANCE = 0.16         # m: a bump's centre is this far from every object's centre
TABLE_MARGIN = 0.08             # m inside the tabletop's edge
ARTEFACTS_FILE = "gt/artefacts.json"


def _logit(p):
    p = np.clip(np.asarray(p, np.float64), 1e-4, 1 - 1e-4)
    return np.log(p / (1 - p)).astype(np.float32)


def _gaussians(means, sigma, flatten, rgb, opacity, degree_coeffs: int) -> GaussianSplatData:
    n = len(means)
    sh = np.zeros((n, degree_coeffs, 3), np.float32)
    sh[:, 0] = (np.asarray(rgb) - 0.5) / 0.28209479177387814
    scales = np.stack([sigma, sigma, sigma * flatten], axis=1)
    return GaussianSplatData(means=np.asarray(means, np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                             log_scales=np.log(scales).astype(np.float32), opacity_logits=_logit(opacity), sh=sh)


def _table(capture: GaussianSplatData, labels: np.ndarray, object_xy: np.ndarray, top_z: float):
    """The tabletop's Gaussians (background, within 1 cm of its height) and its (x, y) box."""
    on_top = (labels == 0) & (np.abs(capture.means[:, 2] - top_z) < 0.01)
    xy = capture.means[on_top, :2].astype(np.float64)
    if len(xy) < 10:
        raise ValueError("no tabletop Gaussians found at the objects' base height")
    return on_top, np.percentile(xy, 1, axis=0), np.percentile(xy, 99, axis=0)


def add_artefacts(scene_dir: str | Path, seed: int = 0, bumps: int = 4, floaters: int = 4) -> list[dict]:
    """Add ``bumps`` floor bumps and ``floaters`` floater clouds to a synthesized folder's capture
    (module docstring); returns the records written to ``gt/artefacts.json``."""
    scene_dir = Path(scene_dir)
    if (scene_dir / ARTEFACTS_FILE).exists():
        raise ValueError(f"{scene_dir}: artefacts were already added ({ARTEFACTS_FILE})")
    truth = json.loads((scene_dir / "gt" / "objects.json").read_text())
    poses = np.array([np.asarray(t["pose"], np.float64) for t in truth])
    object_xy, top_z = poses[:, :2, 3], float(np.median(poses[:, 2, 3]))
    capture = read_gaussian_ply(scene_dir / "point_cloud.ply")
    labels = np.load(scene_dir / "gt" / "labels.npy")
    on_top, lo, hi = _table(capture, labels, object_xy, top_z)
    table_rgb = np.clip(capture.sh[on_top, 0] * 0.28209479177387814 + 0.5, 0, 1)
    rng = np.random.default_rng(seed)
    coeffs = capture.sh.shape[1]
    parts, records = [capture], []
    for _ in range(bumps):
        for _try in range(200):
            centre = rng.uniform(lo + TABLE_MARGIN, hi - TABLE_MARGIN)
            if np.all(np.linalg.norm(object_xy - centre, axis=1) > OBJECT_CLEARANCE) and all(
                    np.linalg.norm(np.asarray(r["centre"][:2]) - centre) > 2 * BUMP_RADIUS[1] for r in records):
                break
        else:
            break
        radius, height = rng.uniform(*BUMP_RADIUS), rng.uniform(*BUMP_HEIGHT)
        count = int(np.pi * radius**2 / BUMP_SPACING**2)
        r = radius * np.sqrt(rng.uniform(0, 1, count))
        a = rng.uniform(0, 2 * np.pi, count)
        xy = centre + np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
        z = top_z + height * (1 - (r / radius) ** 2)
        rgb = np.clip(table_rgb[rng.integers(0, len(table_rgb), count)] + 0.03 * rng.normal(size=(count, 3)), 0, 1)
        parts.append(_gaussians(np.column_stack([xy, z]), np.full(count, 0.6 * BUMP_SPACING), 0.3, rgb,
                                rng.uniform(0.85, 0.99, count), coeffs))
        records.append({"kind": "bump", "centre": [*centre.round(4).tolist(), round(top_z, 4)],
                        "radius": round(float(radius), 4), "height": round(float(height), 4), "gaussians": count})
    for _ in range(floaters):
        centre = np.array([*rng.uniform(lo, hi), top_z + rng.uniform(*FLOATER_HEIGHT)])
        means = centre + 0.015 * rng.normal(size=(FLOATER_BLOBS, 3))
        parts.append(_gaussians(means, rng.uniform(0.005, 0.012, FLOATER_BLOBS), 1.0,
                                np.tile(rng.uniform(0.2, 0.9, 3), (FLOATER_BLOBS, 1)),
                                rng.uniform(0.3, 0.8, FLOATER_BLOBS), coeffs))
        records.append({"kind": "floater", "centre": centre.round(4).tolist(), "radius": 0.03,
                        "height": 0.0, "gaussians": FLOATER_BLOBS})
    added = sum(p.num for p in parts[1:])
    joined = GaussianSplatData.join(parts, like=capture)
    write_gaussian_ply(scene_dir / "point_cloud.ply", joined)
    buf = io.BytesIO()
    np.save(buf, np.concatenate([labels, np.zeros(added, labels.dtype)]))
    write_bytes(scene_dir / "gt" / "labels.npy", buf.getvalue())
    write_text(scene_dir / ARTEFACTS_FILE, json.dumps({"seed": seed, "artefacts": records}, indent=2))
    return records
