"""A 3DGS "capture" sampled from surfaces: flat, surface-aligned disk Gaussians.

What a trained 3DGS model of the scene looks like, with its usual defects:
area-weighted density, a thin disk per sample (normal = the disk's short axis),
SH degree 3 with a mild view-dependent lobe that turns with the surface, a few
floaters, blurry low-opacity Gaussians straddling object/table contact lines, and
nothing under the objects' contact patches (that tabletop was never seen).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from phirie_jax.rotations import matrix_to_quat
from phirie_jax.synthetic.shapes import ColourFn
from phirie_jax.types import GaussianSplatData

DISK_THICKNESS = 0.12   # short axis / long axis of a surface disk
DISK_RADIUS = 0.9       # long-axis σ as a fraction of the sample spacing
SURFACE_OPACITY = 0.92
SH_DEGREE = 3


def _logit(p):
    p = np.clip(p, 1e-6, 1 - 1e-6)
    return np.log(p / (1 - p))


def _rgb_to_dc(rgb):
    return (rgb - 0.5) / 0.28209479177387814


@dataclasses.dataclass(frozen=True)
class LabelledGaussians:
    """Gaussians plus a per-Gaussian instance label (0 = background)."""

    data: GaussianSplatData
    labels: np.ndarray  # (N,) uint16

    @staticmethod
    def concatenate(parts: list["LabelledGaussians"]) -> "LabelledGaussians":
        fields = ("means", "quats", "log_scales", "opacity_logits", "sh")
        data = GaussianSplatData(**{f: np.concatenate([getattr(p.data, f) for p in parts]) for f in fields})
        return LabelledGaussians(data, np.concatenate([p.labels for p in parts]))

    def subset(self, keep: np.ndarray) -> "LabelledGaussians":
        return LabelledGaussians(self.data.subset(keep), self.labels[keep])


def tangent_frames(normals: np.ndarray) -> np.ndarray:
    """(P, 3) unit normals → (P, 3, 3) rotations whose third column is the normal."""
    helper = np.where(np.abs(normals[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    return np.stack([t1, t2, normals], axis=-1)


def view_lobe(shininess: float, rng: np.random.Generator) -> np.ndarray:
    """(16, 3) SH coefficients (DC zero) of a soft lobe about the local +z, in the disk's frame."""
    lobe = np.zeros((16, 3))
    lobe[2] = 0.9  # band-1 z term: brighter when seen along the normal
    lobe[6] = 0.4  # band-2 zonal term sharpens it
    lobe[12] = 0.15
    lobe[1:] += 0.15 * rng.normal(size=(15, 1))  # a little anisotropy, grey (colourless)
    return shininess * lobe


def rotated_lobes(lobe: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """(16, 3) local lobe, (P, 3, 3) frames → (P, 16, 3) world-frame coefficients."""
    from kernels.sh import rotate_sh

    return rotate_sh(np.broadcast_to(lobe, (len(rotations), 16, 3)), rotations)


def sample_surface(mesh, spacing: float, rng: np.random.Generator):
    """Area-weighted points on ``mesh`` at about one per spacing²: (P, 3) points, (P, 3) normals."""
    import trimesh

    count = max(16, int(round(mesh.area / spacing**2)))
    points, faces = trimesh.sample.sample_surface(mesh, count, seed=int(rng.integers(2**31)))
    return np.asarray(points), np.asarray(mesh.face_normals[faces])


def surface_gaussians(points, normals, colour: ColourFn, colour_points, spacing: float,
                      label: int, shininess: float, rng: np.random.Generator) -> LabelledGaussians:
    """Flat disks on the sampled surface, coloured by ``colour(colour_points)`` (canonical frame)."""
    n = len(points)
    frames = tangent_frames(normals)
    quats = matrix_to_quat(frames)
    sigma = DISK_RADIUS * spacing * rng.uniform(0.8, 1.2, size=(n, 1))
    log_scales = np.log(np.concatenate([sigma, sigma, DISK_THICKNESS * sigma], axis=1))
    rgb = np.clip(colour(colour_points) + 0.02 * rng.normal(size=(n, 3)), 0, 1)
    sh = rotated_lobes(view_lobe(shininess, rng), frames)
    sh[:, 0] = _rgb_to_dc(rgb)
    opacity = _logit(np.full(n, SURFACE_OPACITY) + rng.uniform(-0.04, 0.04, n))
    data = GaussianSplatData(
        means=points.astype(np.float32), quats=quats.astype(np.float32),
        log_scales=log_scales.astype(np.float32), opacity_logits=opacity.astype(np.float32),
        sh=sh.astype(np.float32))
    return LabelledGaussians(data, np.full(n, label, np.uint16))


def blob_gaussians(centres, sigma, rgb, opacity, label: int | np.ndarray) -> LabelledGaussians:
    """Isotropic, view-independent Gaussians (floaters, boundary blur)."""
    n = len(centres)
    sh = np.zeros((n, 16, 3), np.float32)
    sh[:, 0] = _rgb_to_dc(np.asarray(rgb))
    data = GaussianSplatData(
        means=np.asarray(centres, np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        log_scales=np.repeat(np.log(np.asarray(sigma, np.float32)).reshape(-1, 1), 3, axis=1),
        opacity_logits=_logit(np.asarray(opacity)).astype(np.float32), sh=sh)
    labels = np.broadcast_to(np.asarray(label, np.uint16), (n,)).copy()
    return LabelledGaussians(data, labels)
