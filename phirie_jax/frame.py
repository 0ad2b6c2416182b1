"""The scene frame: which way is up. Decided here, recorded once in the manifest's ``frame``
section, and read back by every later stage (``Manifest.up``); no stage derives it otherwise.

Up starts from the best estimate available — the observation stage's support-plane RANSAC
(automatic masks), else the cameras' mean image-up direction, else +z — and is refined by
the normals of the supports the instances stand on, when they agree with it to within
``MAX_UP_CHANGE_DEG``. The gravity frame is the world rotated so that up is +z (no
translation): registration and the built-in generators work in it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from phirie_jax.geometry import rotation_to_z
from phirie_jax.types import Camera

MIN_PLANE_HITS = 20        # support rays needed before a support's normal may refine up
MAX_UP_CHANGE_DEG = 15.0   # refinement never moves up more than this
DEFAULT_UP = (0.0, 0.0, 1.0)


@dataclasses.dataclass(frozen=True)
class GravityFrame:
    rotation: np.ndarray  # (3, 3) world → gravity (x_g = R x_w); R @ up = +z
    up: np.ndarray        # (3,) unit world up
    source: str           # where up came from

    def to_gravity(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) world points → (N, 3) gravity-frame points."""
        return points @ self.rotation.T

    def to_world(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) gravity-frame points → (N, 3) world points."""
        return points @ self.rotation

    def matrix(self) -> np.ndarray:
        """(4, 4) gravity → world."""
        out = np.eye(4)
        out[:3, :3] = self.rotation.T
        return out

    def record(self) -> dict:
        """The manifest's ``frame`` section."""
        return {"up": self.up, "up_source": self.source}


def gravity_frame(up: np.ndarray, source: str) -> GravityFrame:
    """The frame whose +z is ``up`` (3,), any length > 0."""
    up = np.asarray(up, np.float64)
    up = up / np.linalg.norm(up)
    return GravityFrame(rotation_to_z(up), up, source)


def camera_up(cameras: list[Camera] | tuple[Camera, ...]) -> np.ndarray:
    """(3,) mean image-up direction (−y of OpenCV cameras) in world coordinates; +z without cameras."""
    ups = [-c.world_to_camera[1, :3] for c in cameras]
    mean = np.mean(ups, axis=0) if ups else np.zeros(3)
    norm = np.linalg.norm(mean)
    return mean / norm if norm > 1e-6 else np.array(DEFAULT_UP)


def initial_frame(cameras: tuple[Camera, ...], observed_up: np.ndarray | None = None) -> GravityFrame:
    """The first estimate: the observation stage's (3,) up when it made one, else the cameras'."""
    if observed_up is not None:
        return gravity_frame(observed_up, "observe (automatic masks)")
    if cameras:
        return gravity_frame(camera_up(cameras), "cameras (mean image up)")
    return gravity_frame(np.array(DEFAULT_UP), "default +z")


def refine_frame(frame: GravityFrame, normals: np.ndarray, hits: np.ndarray) -> GravityFrame:
    """Up refined to the hit-weighted mean of support-plane normals (K, 3) (gravity frame, each
    fitted from ``hits`` (K,) rays; fits from fewer than ``MIN_PLANE_HITS`` are ignored), unless
    that moves it more than ``MAX_UP_CHANGE_DEG``."""
    normals, hits = np.asarray(normals, np.float64).reshape(-1, 3), np.asarray(hits, np.float64).reshape(-1)
    keep = hits >= MIN_PLANE_HITS
    if not keep.any():
        return frame
    n = (normals[keep] * hits[keep, None]).sum(0)
    n /= np.linalg.norm(n)
    if np.degrees(np.arccos(np.clip(n[2], -1, 1))) > MAX_UP_CHANGE_DEG:
        return frame
    up = frame.to_world(n[None])[0]
    return GravityFrame(rotation_to_z(up), up / np.linalg.norm(up), frame.source + "+support plane")
