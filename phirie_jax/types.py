"""The pipeline's shared records: a camera, a host-side Gaussian set, a loaded scene.

Readers in ``io/`` build them from files; every stage takes them from here.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from phirie_jax.errors import SceneInputError


@dataclasses.dataclass(frozen=True)
class Camera:
    name: str                       # image file name, relative to the image folder
    K: np.ndarray                   # (3, 3) float64 pinhole intrinsics
    world_to_camera: np.ndarray     # (4, 4) float64 rigid transform, OpenCV axes
    width: int
    height: int
    model: str = "PINHOLE"          # source camera model name (COLMAP spelling)
    distortion: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))  # (D,)
    image_path: Path | None = None  # absolute path of the image, when known

    @property
    def is_distorted(self) -> bool:
        return bool(np.any(self.distortion != 0.0))

    @property
    def camera_to_world(self) -> np.ndarray:
        """(4, 4) inverse of ``world_to_camera`` (rigid, so Rᵀ and −Rᵀt)."""
        rot = self.world_to_camera[:3, :3]
        out = np.eye(4)
        out[:3, :3] = rot.T
        out[:3, 3] = -rot.T @ self.world_to_camera[:3, 3]
        return out

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates."""
        return self.camera_to_world[:3, 3]

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pinhole projection of world points (N, 3) → pixel coords (N, 2), depth (N,)."""
        cam = points @ self.world_to_camera[:3, :3].T + self.world_to_camera[:3, 3]
        depth = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (cam @ self.K.T)[:, :2] / depth[:, None]
        return uv, depth

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by ``factor`` (pixel-centre convention kept)."""
        K = self.K.copy()
        K[:2] *= factor
        return dataclasses.replace(
            self, K=K, width=int(round(self.width * factor)), height=int(round(self.height * factor))
        )


@dataclasses.dataclass(frozen=True)
class GaussianSplatData:
    """Host-side Gaussian set as stored in a 3DGS PLY (NumPy arrays)."""

    means: np.ndarray           # (N, 3)
    quats: np.ndarray           # (N, 4) wxyz as stored (not normalized)
    log_scales: np.ndarray      # (N, 3)
    opacity_logits: np.ndarray  # (N,)
    sh: np.ndarray              # (N, K, 3), K = (degree + 1)²
    extra: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)  # name → (N,)
    layout: tuple[tuple[str, str], ...] = ()  # file property order and type tokens
    comments: tuple[str, ...] = ()

    @property
    def num(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return int(round(np.sqrt(self.sh.shape[1]))) - 1

    def bounds(self) -> np.ndarray:
        """(2, 3) axis-aligned min and max of the means."""
        return np.stack([self.means.min(0), self.means.max(0)]) if self.num else np.zeros((2, 3))

    def to_host_kernel(self):
        """The same set as a ``kernels.gaussians.Gaussians`` of NumPy float32 arrays: for sets
        assembled on the host before one move to the device (``jax.device_put``)."""
        from kernels.gaussians import Gaussians

        return Gaussians(*(np.asarray(x, np.float32) for x in
                           (self.means, self.quats, self.log_scales, self.opacity_logits, self.sh)))

    def to_kernel(self, dtype=None):
        """The same set as a ``kernels.gaussians.Gaussians`` of JAX arrays (float32 by default)."""
        import jax.numpy as jnp

        from kernels.gaussians import Gaussians

        dtype = dtype or jnp.float32
        return Gaussians(
            means=jnp.asarray(self.means, dtype),
            quats=jnp.asarray(self.quats, dtype),
            log_scales=jnp.asarray(self.log_scales, dtype),
            opacity_logits=jnp.asarray(self.opacity_logits, dtype),
            sh=jnp.asarray(self.sh, dtype),
        )

    @staticmethod
    def from_kernel(gaussians, extra: dict[str, np.ndarray] | None = None) -> "GaussianSplatData":
        """Host copy (float32) of a ``kernels.gaussians.Gaussians``."""
        return GaussianSplatData(
            means=np.asarray(gaussians.means, np.float32),
            quats=np.asarray(gaussians.quats, np.float32),
            log_scales=np.asarray(gaussians.log_scales, np.float32),
            opacity_logits=np.asarray(gaussians.opacity_logits, np.float32),
            sh=np.asarray(gaussians.sh, np.float32),
            extra=dict(extra or {}),
        )

    @staticmethod
    def join(parts: "list[GaussianSplatData]", like: "GaussianSplatData | None" = None) -> "GaussianSplatData":
        """The sets one after another (float32). SH is padded with zeros (or cut) to ``like``'s
        degree, else to the highest of ``parts``; ``like``'s extra properties are kept (zeros for
        sets without them), with its file layout and comments."""
        k = like.sh.shape[1] if like is not None else max(p.sh.shape[1] for p in parts)

        def sh(p: GaussianSplatData) -> np.ndarray:
            out = np.zeros((p.num, k, 3), np.float32)
            out[:, : min(k, p.sh.shape[1])] = p.sh[:, :k]
            return out

        extra = {} if like is None else {
            name: np.concatenate([p.extra.get(name, np.zeros(p.num, values.dtype)) for p in parts])
            for name, values in like.extra.items()}
        return GaussianSplatData(
            means=np.concatenate([p.means for p in parts]).astype(np.float32),
            quats=np.concatenate([p.quats for p in parts]).astype(np.float32),
            log_scales=np.concatenate([p.log_scales for p in parts]).astype(np.float32),
            opacity_logits=np.concatenate([p.opacity_logits for p in parts]).astype(np.float32),
            sh=np.concatenate([sh(p) for p in parts]), extra=extra,
            layout=like.layout if like is not None else (), comments=like.comments if like is not None else ())

    def subset(self, index: np.ndarray) -> "GaussianSplatData":
        """The Gaussians selected by ``index`` (boolean mask or integer indices), extras included."""
        return dataclasses.replace(
            self,
            means=self.means[index],
            quats=self.quats[index],
            log_scales=self.log_scales[index],
            opacity_logits=self.opacity_logits[index],
            sh=self.sh[index],
            extra={k: v[index] for k, v in self.extra.items()},
        )


GAUSSIAN_NAMES = ("point_cloud.ply", "splat.ply")


@dataclasses.dataclass(frozen=True)
class CandidateFiles:
    """One externally generated candidate for an instance: a mesh and optional Gaussians."""

    instance_id: int
    name: str
    mesh: Path
    gaussians: Path | None = None


@dataclasses.dataclass(frozen=True)
class SceneInput:
    """Everything a scene folder provides. Paths are absolute; arrays are NumPy."""

    root: Path
    layout: str                                  # "colmap" | "nerfstudio" | "scannetpp" | "gaussians"
    gaussians: GaussianSplatData | None
    gaussians_path: Path | None
    cameras: tuple[Camera, ...] = ()             # camera k = k-th image in name order
    camera_source: Path | None = None
    sparse_points: np.ndarray | None = None      # (P, 3) COLMAP points, when present
    surface_mesh: Path | None = None
    masks: tuple[Path | None, ...] | None = None  # aligned with ``cameras``
    candidates: dict[int, tuple[CandidateFiles, ...]] = dataclasses.field(default_factory=dict)
    segments_anno: Path | None = None
    # (4, 4) Sim(3) the Gaussians, cameras and sparse points were moved by (``phirie_jax.frame``);
    # None: they are as the files hold them
    capture_to_world: np.ndarray | None = None

    def to_world(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) points read from a file of the capture (e.g. the scan mesh) in the scene's frame."""
        points = np.asarray(points, np.float64)
        if self.capture_to_world is None:
            return points
        return points @ self.capture_to_world[:3, :3].T + self.capture_to_world[:3, 3]

    @property
    def image_paths(self) -> tuple[Path | None, ...]:
        return tuple(c.image_path for c in self.cameras)

    def require_gaussians(self) -> GaussianSplatData:
        if self.gaussians is None:
            raise SceneInputError(self.root, "gaussians",
                                  f"no Gaussian PLY found (expected --gaussians PATH, "
                                  f"{' or '.join(GAUSSIAN_NAMES)}, or point_cloud/iteration_*/point_cloud.ply)")
        return self.gaussians

    def require_cameras(self) -> tuple[Camera, ...]:
        if not self.cameras:
            raise SceneInputError(self.root, "cameras",
                                  "none found (expected sparse/0/, sparse/, transforms.json or dslr/)")
        return self.cameras

    def bounds(self) -> np.ndarray | None:
        """(2, 3) scene bounds: Gaussian means, else COLMAP points, else camera centres."""
        if self.gaussians is not None and self.gaussians.num:
            return self.gaussians.bounds()
        for pts in (self.sparse_points, np.array([c.center for c in self.cameras]).reshape(-1, 3)):
            if pts is not None and len(pts):
                return np.stack([pts.min(0), pts.max(0)])
        return None
