"""The gravity frame of a world whose up is known: the world rotated so that up is +z.

Scenes converted with a resolved frame (``phirie_jax.frame.resolve``) are already +z up, so
their gravity frame is the identity; output folders written before the ``frame`` section
recorded another up, which this still honours. Registration and the built-in generators
work in it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from phirie_jax.geometry import rotation_to_z

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


def gravity_frame(up: np.ndarray, source: str) -> GravityFrame:
    """The frame whose +z is ``up`` (3,), any length > 0."""
    up = np.asarray(up, np.float64)
    up = up / np.linalg.norm(up)
    return GravityFrame(rotation_to_z(up), up, source)
