"""The scene frame, resolved once before observation and applied to the whole capture.

``capture_to_world`` is the Sim(3) x_w = s R x_c: R the smallest rotation taking the
capture's up to +z, s metres per capture unit, no translation (the capture's origin stays
the world's). Gaussians (means, orientations, sizes and SH), cameras (depths in metres)
and sparse points are moved into the world here; files still in the capture's frame (a scan
mesh) are moved when read (``SceneInput.to_world``). The manifest's ``frame`` section
records it (``SceneFrame.record``), and ``Manifest.up`` reads +z from it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from phirie_jax.errors import SceneInputError
from phirie_jax.frame import estimate
from phirie_jax.frame.config import FrameConfig
from phirie_jax.geometry import rotation_to_z, sim3_matrix, split_sim3
from phirie_jax.types import Camera, GaussianSplatData, SceneInput

KNOWN_SIZE_UNCERTAINTY = 1.05  # an instance's observed longest side: partly seen, a few % short
SEED = 0


@dataclasses.dataclass(frozen=True)
class SceneFrame:
    capture_to_world: np.ndarray  # (4, 4) Sim(3)
    capture_up: np.ndarray        # (3,) up in capture coordinates
    up_source: str
    scale_source: str
    scale_uncertainty: float      # multiplicative: the true scale is within [s / f, s · f]
    evidence: dict = dataclasses.field(default_factory=dict)

    @property
    def scale(self) -> float:
        return split_sim3(self.capture_to_world)[0]

    @property
    def is_identity(self) -> bool:
        return bool(np.array_equal(self.capture_to_world, np.eye(4)))

    def record(self) -> dict:
        """The manifest's ``frame`` section."""
        return {"capture_to_world": self.capture_to_world.tolist(), "up": [0.0, 0.0, 1.0],
                "capture_up": self.capture_up.round(8).tolist(), "scale": self.scale,
                "up_source": self.up_source, "scale_source": self.scale_source,
                "scale_uncertainty": self.scale_uncertainty, "evidence": self.evidence}

    def rescaled(self, scale: float, source: str, uncertainty: float) -> "SceneFrame":
        """The same up with another number of metres per capture unit."""
        rotation = split_sim3(self.capture_to_world)[1]
        return dataclasses.replace(self, capture_to_world=sim3_matrix(scale, rotation, np.zeros(3)),
                                   scale_source=source, scale_uncertainty=uncertainty)

    def apply(self, scene: SceneInput) -> SceneInput:
        """The scene in the world frame (the identity frame returns it as it is)."""
        return scene_in_world(scene, self.capture_to_world)


def world_gaussians(gaussians: GaussianSplatData, capture_to_world: np.ndarray) -> GaussianSplatData:
    """The Gaussians moved by a (4, 4) Sim(3): means, orientations, sizes and SH (``kernels.gaussians``)."""
    import jax.numpy as jnp

    from kernels.gaussians import Sim3, transform_gaussians

    moved = transform_gaussians(gaussians.to_kernel(), Sim3.from_matrix(jnp.asarray(capture_to_world, jnp.float32)))
    return dataclasses.replace(GaussianSplatData.from_kernel(moved, gaussians.extra),
                               layout=gaussians.layout, comments=gaussians.comments)


def scene_in_world(scene: SceneInput, capture_to_world: np.ndarray | None) -> SceneInput:
    """The scene's Gaussians, cameras and sparse points moved by a (4, 4) Sim(3) (None or the
    identity: the scene as it is)."""
    if capture_to_world is None or np.array_equal(capture_to_world, np.eye(4)):
        return scene
    if scene.capture_to_world is not None:
        raise ValueError("scene already moved into a world frame")
    moved = dataclasses.replace(scene, capture_to_world=np.asarray(capture_to_world, np.float64))
    return dataclasses.replace(
        moved, gaussians=None if scene.gaussians is None else world_gaussians(scene.gaussians, moved.capture_to_world),
        cameras=tuple(world_camera(c, moved.capture_to_world) for c in scene.cameras),
        sparse_points=None if scene.sparse_points is None else moved.to_world(scene.sparse_points))


def world_camera(camera: Camera, capture_to_world: np.ndarray) -> Camera:
    """The camera in the world of a (4, 4) Sim(3) x_w = s R x_c + t: world-to-camera rotation
    E_R Rᵀ, translation s E_t − E_R Rᵀ t (camera depths become metres)."""
    scale, rotation, translation = split_sim3(capture_to_world)
    e_rot, e_t = camera.world_to_camera[:3, :3], camera.world_to_camera[:3, 3]
    out = np.eye(4)
    out[:3, :3] = e_rot @ rotation.T
    out[:3, 3] = scale * e_t - e_rot @ rotation.T @ translation
    return dataclasses.replace(camera, world_to_camera=out)


def _up(scene: SceneInput, config: FrameConfig, rng) -> tuple[np.ndarray, str, list, float | None]:
    """(capture up, its source, the oriented planes found, cameras' distance to the scene)."""
    planes, distance = [], None
    if scene.gaussians is not None and scene.cameras:
        try:
            points, distance = estimate.visible_centres(scene.gaussians, scene.cameras, rng)
            found = estimate.find_planes(points, estimate.PLANE_THRESHOLD * distance, rng)
            planes = estimate.oriented_planes(found, scene.cameras, len(points))
        except ValueError:
            planes, distance = [], None
    if config.up_axis is not None:
        return config.up_axis, f"given (--up {config.up})", planes, distance
    if not scene.cameras:
        return np.array([0.0, 0.0, 1.0]), "default +z (no cameras)", planes, distance
    up, source = estimate.estimate_up(planes, scene.cameras)
    return up, source, planes, distance


def _scale(scene: SceneInput, config: FrameConfig, up: np.ndarray, planes: list, distance: float | None
           ) -> tuple[float, str, float]:
    if config.scale is not None:
        return config.scale, "given (--scale)", 1.0
    if config.metric:
        return 1.0, "declared metric", 1.0
    if scene.layout == "scannetpp":
        return 1.0, "ScanNet++ (metric)", 1.0
    if config.known_distance is not None:
        values = np.asarray(config.known_distance, np.float64)
        return values[6] / float(np.linalg.norm(values[3:6] - values[:3])), "given (--known-distance)", 1.0
    if distance is None:
        raise SceneInputError(scene.root, "scale", "cannot be estimated without Gaussians in front of the "
                              "cameras (expected --scale, --known-distance or --metric)")
    return estimate.estimate_scale(planes, up, scene.cameras, distance)


def resolve_frame(scene: SceneInput, config: FrameConfig = FrameConfig()) -> SceneFrame:
    """Up and metres per unit of the capture (given, declared or estimated) as one frame.
    ``--known-size`` is applied later (``with_known_size``): it needs the observed instances."""
    rng = np.random.default_rng(SEED)
    up, up_source, planes, distance = _up(scene, config, rng)
    up = up / np.linalg.norm(up)
    scale, scale_source, uncertainty = _scale(scene, config, up, planes, distance)
    evidence = {"planes": [p.as_dict() for p in planes], "camera_up_vote": estimate.cameras_up(scene.cameras)
                .round(6).tolist(), "camera_distance": distance}
    rotation = rotation_to_z(up)
    matrix = sim3_matrix(scale, rotation, np.zeros(3))
    if np.allclose(matrix, np.eye(4), atol=1e-12):
        matrix = np.eye(4)
    return SceneFrame(matrix, up, up_source, scale_source, uncertainty, evidence)


def longest_side(points: np.ndarray) -> float:
    """The longest side of the (N, 3) world points' box: height along +z, and the two sides of
    their horizontal principal axes."""
    xy = points[:, :2] - points[:, :2].mean(0)
    axes = np.linalg.svd(xy, full_matrices=False)[2] if len(points) > 2 else np.eye(2)
    sides = np.ptp(xy @ axes.T, axis=0)
    return float(max(sides.max(), np.ptp(points[:, 2])))


def with_known_size(frame: SceneFrame, points: np.ndarray, instance_id: int, metres: float) -> SceneFrame:
    """The frame rescaled so instance ``instance_id``'s observed points (N, 3), world, made at
    ``frame``'s scale, have ``metres`` as their longest side."""
    side = longest_side(points)
    if not side > 0:
        raise SceneInputError(None, "--known-size", f"instance {instance_id} has no extent to measure")
    return frame.rescaled(frame.scale * metres / side,
                          f"given (--known-size {instance_id}={metres}: observed longest side)", KNOWN_SIZE_UNCERTAINTY)
