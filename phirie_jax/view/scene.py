"""What the viewer sends to the browser, as plain arrays (no viser here, so it is tested alone).

viser's Gaussian splat node (viser 1.1, ``SceneApi.add_gaussian_splats``) takes centres (N, 3),
covariances (N, 3, 3), RGB (N, 3) and opacities (N, 1): one colour per Gaussian, no spherical
harmonics. The viewer therefore draws each Gaussian with its SH degree-0 colour (its view-averaged
colour, ``kernels.sh.sh_to_rgb`` of the DC band alone); the renderer behind ``phirie render``,
the report and the rollouts evaluates every band.

Object nodes: each object's Gaussians are sent once, placed at t = 0 (the environment's own
``Environment.gaussians``). The node then carries the motion since t = 0,
S_i(t) S_i(0)⁻¹ = T_i(t) T_i(0)⁻¹ (``node_motion``: a rigid transform, taken from the environment's
``placements``), so a pose update moves the node without sending its Gaussians again.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from kernels.gaussians import Gaussians
from kernels.sh import sh_to_rgb
from phirie_jax.geometry import split_sim3
from phirie_jax.rotations import matrix_to_quat, quat_to_matrix
from phirie_jax.types import Camera

RIGID_TOL = 1e-6   # a node motion's scale may differ from 1 by float64 round-off only

# Instance colours (0–255), distinct on the grey floors and tables of captures; cycled.
PALETTE = ((230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200), (245, 130, 48), (145, 30, 180),
           (70, 240, 240), (240, 50, 230), (210, 245, 60), (0, 128, 128), (170, 110, 40), (128, 0, 0))


@dataclasses.dataclass(frozen=True)
class SplatArrays:
    """One splat node's arrays, as viser takes them."""

    centers: np.ndarray       # (N, 3) float32
    covariances: np.ndarray   # (N, 3, 3) float32
    rgbs: np.ndarray          # (N, 3) float32 in [0, 1]
    opacities: np.ndarray     # (N, 1) float32 in [0, 1]

    @property
    def num(self) -> int:
        return len(self.centers)

    def coloured(self, rgb) -> "SplatArrays":
        """The same Gaussians in one colour ``rgb`` (3,) in [0, 1] (instance colours)."""
        return dataclasses.replace(self, rgbs=np.tile(np.asarray(rgb, np.float32), (self.num, 1)))

    def rows(self, rows: slice) -> "SplatArrays":
        return SplatArrays(self.centers[rows], self.covariances[rows], self.rgbs[rows], self.opacities[rows])


def splat_arrays(gaussians: Gaussians) -> SplatArrays:
    """viser's arrays of a Gaussian set: world covariances R diag(s²) Rᵀ, the degree-0 colour
    clamped to [0, 1], opacity = sigmoid(logit)."""
    dc = jnp.asarray(gaussians.sh)[:, :1]                            # (N, 1, 3)
    rgb = sh_to_rgb(dc, jnp.zeros((gaussians.num, 3)))               # the DC band ignores the direction
    return SplatArrays(np.asarray(gaussians.means, np.float32),
                       np.asarray(gaussians.covariances(), np.float32),
                       np.clip(np.asarray(rgb, np.float32), 0.0, 1.0),
                       np.asarray(gaussians.opacities, np.float32)[:, None])


def palette_colour(index: int) -> tuple[float, float, float]:
    """Instance colour ``index`` (cycled), rgb in [0, 1]."""
    return tuple(c / 255.0 for c in PALETTE[index % len(PALETTE)])


def node_motion(placement: np.ndarray, placement0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(wxyz (4,), position (3,)) of S(t) S(0)⁻¹ for an object's placements S(t), S(0) (4, 4):
    its rigid motion since t = 0 (``ValueError`` if it is not rigid)."""
    motion = np.asarray(placement, np.float64) @ np.linalg.inv(np.asarray(placement0, np.float64))
    scale, rotation, translation = split_sim3(motion)
    if abs(scale - 1.0) > RIGID_TOL:
        raise ValueError(f"an object's motion since t = 0 scales by {scale} (expected a rigid motion)")
    return matrix_to_quat(rotation), translation


def placed_vertices(vertices: np.ndarray, placement: np.ndarray) -> np.ndarray:
    """(V, 3) canonical mesh vertices placed by a Sim(3) (4, 4)."""
    placement = np.asarray(placement, np.float64)
    return np.asarray(vertices, np.float64) @ placement[:3, :3].T + placement[:3, 3]


@dataclasses.dataclass(frozen=True)
class CameraView:
    """A capture camera as a viser camera (and frustum): OpenCV axes, like ours."""

    fov: float                # vertical field of view, radians
    aspect: float             # width / height
    wxyz: np.ndarray          # (4,) camera → world rotation
    position: np.ndarray      # (3,) camera centre

    def look_at(self, distance: float) -> np.ndarray:
        """(3,) the point ``distance`` metres ahead along the optical axis."""
        rot = quat_to_matrix(self.wxyz)
        return self.position + distance * rot[:, 2]


def camera_view(camera: Camera) -> CameraView:
    """The viser view of a pinhole camera (its principal point is taken as the image centre)."""
    c2w = camera.camera_to_world
    fov = 2.0 * np.arctan(0.5 * camera.height / camera.K[1, 1])
    return CameraView(float(fov), camera.width / camera.height,
                      matrix_to_quat(c2w[:3, :3]), c2w[:3, 3].copy())


def screen_position(point: np.ndarray, view: CameraView) -> tuple[float, float] | None:
    """Where a world point (3,) appears in a view, in viser's screen coordinates (0–1, (0, 0)
    top-left, OpenCV axes), or None behind the camera."""
    rot = quat_to_matrix(view.wxyz)
    x, y, z = rot.T @ (np.asarray(point, np.float64) - view.position)
    if z <= 0:
        return None
    focal = 0.5 / np.tan(0.5 * view.fov)   # in image heights
    return 0.5 + focal * x / (z * view.aspect), 0.5 + focal * y / z
