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
import functools

import numpy as np

from phirie_jax.errors import SceneInputError
from phirie_jax.frame import estimate, priors
from phirie_jax.frame.config import FrameConfig
from phirie_jax.frame.cues import (
    STILL_VOTE_SIGMA_DEG,
    SUPPORT_SEARCH_DEG,
    VOTE_SIGMA_DEG,
    Cue,
    UpDecision,
    consensus,
    decide_up,
)
from phirie_jax.geometry import rotation_to_z, sim3_matrix, split_sim3
from phirie_jax.types import Camera, GaussianSplatData, SceneInput

KNOWN_SIZE_UNCERTAINTY = 1.05  # an instance's observed longest side: partly seen, a few % short
SEED = 0


@dataclasses.dataclass(frozen=True)
class SupportPlane:
    """The plane things rest on, in the world frame (metres): normal · x = offset, normal ≈ +z
    (a soft support's fitted plane may lean a few degrees), ``point`` on it where its points are."""

    normal: np.ndarray   # (3,) unit, world
    point: np.ndarray    # (3,) world: the centroid of the points it was fitted to
    source: str          # "opaque Gaussian centres" | "splat surface" | "markers"
    inliers: int

    @property
    def offset(self) -> float:
        return float(self.normal @ self.point)

    @property
    def height(self) -> float:
        """The support's z (metres) at ``point``."""
        return float(self.point[2])

    def record(self) -> dict:
        return {"normal": self.normal.round(8).tolist(), "offset": round(self.offset, 8),
                "height": round(self.height, 8), "point": self.point.round(8).tolist(), "source": self.source,
                "inliers": self.inliers}


@dataclasses.dataclass(frozen=True)
class SceneFrame:
    capture_to_world: np.ndarray  # (4, 4) Sim(3)
    capture_up: np.ndarray        # (3,) up in capture coordinates
    up_source: str
    scale_source: str             # starts with "prior:" when no measurement gave the scale
    scale_uncertainty: float      # multiplicative: the true scale is within [s / f, s · f]
    evidence: dict = dataclasses.field(default_factory=dict)
    support_plane: estimate.Plane | None = None   # capture coordinates (``support`` is the world's)
    warnings: tuple[str, ...] = ()

    @property
    def scale(self) -> float:
        return split_sim3(self.capture_to_world)[0]

    @property
    def scale_is_prior(self) -> bool:
        return self.scale_source.startswith("prior:")

    @property
    def is_identity(self) -> bool:
        return bool(np.array_equal(self.capture_to_world, np.eye(4)))

    @property
    def support(self) -> SupportPlane | None:
        """The support plane the frame found, in the world frame (None when there is none: a wall
        capture). Observation's support is this one."""
        plane = self.support_plane
        if plane is None:
            return None
        scale, rotation, translation = split_sim3(self.capture_to_world)
        normal = rotation @ plane.normal
        point = scale * rotation @ plane.centroid + translation
        words = {"centres": "opaque Gaussian centres", "surface": "splat surface", "markers": "markers"}
        return SupportPlane(normal, point, words.get(plane.source, plane.source), plane.inliers)

    def record(self) -> dict:
        """The manifest's ``frame`` section."""
        support = self.support
        return {"capture_to_world": self.capture_to_world.tolist(), "up": [0.0, 0.0, 1.0],
                "capture_up": self.capture_up.round(8).tolist(), "scale": self.scale,
                "up_source": self.up_source, "scale_source": self.scale_source,
                "scale_uncertainty": self.scale_uncertainty, "scale_is_prior": self.scale_is_prior,
                "support": None if support is None else support.record(), "warnings": list(self.warnings),
                "evidence": self.evidence}

    def rescaled(self, scale: float, source: str, uncertainty: float) -> SceneFrame:
        """The same up with another number of metres per capture unit."""
        rotation = split_sim3(self.capture_to_world)[1]
        return dataclasses.replace(self, capture_to_world=sim3_matrix(scale, rotation, np.zeros(3)),
                                   scale_source=source, scale_uncertainty=uncertainty)

    def apply(self, scene: SceneInput) -> SceneInput:
        """The scene in the world frame (the identity frame returns it as it is)."""
        return scene_in_world(scene, self.capture_to_world)


@functools.cache
def _moving_program():
    """``kernels.gaussians.transform_gaussians`` by a (4, 4) matrix, as one compiled program (op by
    op, its few hundred operations each compile on their own on a GPU, for seconds)."""
    import jax

    from kernels.gaussians import Sim3, transform_gaussians

    return jax.jit(lambda gaussians, matrix: transform_gaussians(gaussians, Sim3.from_matrix(matrix)))


def world_gaussians(gaussians: GaussianSplatData, capture_to_world: np.ndarray) -> GaussianSplatData:
    """The Gaussians moved by a (4, 4) Sim(3): means, orientations, sizes and SH (``kernels.gaussians``)."""
    moved = _moving_program()(gaussians.to_kernel(), np.asarray(capture_to_world, np.float32))
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


def _cues(scene: SceneInput, config: FrameConfig, rng) -> tuple[list, list, object, list, float | None, dict,
                                                                 np.ndarray]:
    """(gravity cues, planes of both point sets, orbit, markers, cameras' distance to the scene,
    evidence, both point sets (P, 3)) of a scene with cameras."""
    from phirie_jax.frame import lines
    from phirie_jax.frame.orbit import SIGMA_DEG as ORBIT_SIGMA_DEG
    from phirie_jax.frame.orbit import orbit as find_orbit
    from phirie_jax.frame.surface import surface_points

    vote, turning = estimate.level_vote(scene.cameras)
    cues = [Cue("camera_vote", "cameras' level vote", vote, VOTE_SIGMA_DEG if turning else STILL_VOTE_SIGMA_DEG,
                {"cameras": len(scene.cameras), "turning": turning})]
    evidence: dict = {"camera_up_vote": vote.round(6).tolist()}
    plumb, why = lines.plumb_lines(scene.cameras, vote, rng)
    evidence["plumb_lines"] = plumb.as_dict() if plumb else {"none": why}
    if plumb is not None:
        cues.append(Cue("plumb_lines", f"plumb lines ({plumb.segments} straight edges in {plumb.views} photos)",
                        plumb.up, plumb.sigma_deg, {"segments": plumb.segments, "views": plumb.views}))
    orbit = find_orbit(scene.cameras, vote)
    evidence["orbit"] = None if orbit is None else orbit.as_dict()
    if orbit is not None and orbit.surrounds and orbit.up is not None:
        cues.append(Cue("orbit", "the cameras' orbit", orbit.up, ORBIT_SIGMA_DEG, {"distance": orbit.distance}))
    planes, distance, samples = [], None, [np.zeros((0, 3))]
    if scene.gaussians is not None:
        try:
            points, distance = estimate.visible_centres(scene.gaussians, scene.cameras, rng)
        except ValueError:
            points = None
        if points is not None:
            threshold = estimate.PLANE_THRESHOLD * distance
            surface = surface_points(scene.gaussians, scene.cameras)
            if len(surface) > estimate.MAX_SAMPLES:
                surface = surface[rng.choice(len(surface), estimate.MAX_SAMPLES, replace=False)]
            samples = [points, surface]
            for source, sample in (("centres", points), ("surface", surface)):
                if len(sample) >= 3:
                    planes += estimate.oriented_planes(estimate.find_planes(sample, threshold, rng), scene.cameras,
                                                       len(sample), threshold, source, rng)
    evidence["camera_distance"] = distance
    found = []
    if config.marker_size is not None:
        from phirie_jax.frame import markers

        found = markers.markers(scene.cameras, markers.detect(scene.cameras, config.marker_dictionary))
        evidence["markers"] = [m.as_dict(scene.cameras) for m in found]
        if found:
            normal = np.sum([m.normal(scene.cameras) * len(m.views) for m in found], axis=0)
            cues.append(Cue("markers", f"markers' plane ({len(found)} marker(s))", normal / np.linalg.norm(normal),
                            markers.SIGMA_DEG, {"markers": len(found)}))
    return cues, planes, orbit, found, distance, evidence, np.concatenate(samples)


def _marker_plane(found: list, cameras, up: np.ndarray) -> estimate.Plane | None:
    """The markers' plane as a support candidate (None without markers or when they do not lie flat)."""
    if not found:
        return None
    normal = np.sum([m.normal(cameras) * len(m.views) for m in found], axis=0)
    normal /= np.linalg.norm(normal)
    if estimate.angle_deg(normal, up) > SUPPORT_SEARCH_DEG:
        return None
    corners = np.concatenate([m.corners for m in found])
    centres = np.array([c.center for c in cameras])
    below = int(np.sum(centres @ normal - normal @ corners.mean(0) < 0))
    return estimate.Plane(normal, float(normal @ corners.mean(0)), len(corners), 0.0, "markers", below, corners)


def _scale(scene: SceneInput, config: FrameConfig, up: np.ndarray, decision, planes: list, orbit, found: list,
           distance: float | None, warnings: list, samples: np.ndarray) -> tuple[float, str, float, dict]:
    """(metres per unit, source, ×/÷ band, evidence) given, declared, measured by markers or a prior."""
    if config.scale is not None:
        return config.scale, "given (--scale)", 1.0, {}
    if config.metric:
        return 1.0, "declared metric", 1.0, {}
    if scene.layout == "scannetpp":
        return 1.0, "ScanNet++ (metric)", 1.0, {}
    if config.known_distance is not None:
        values = np.asarray(config.known_distance, np.float64)
        return values[6] / float(np.linalg.norm(values[3:6] - values[:3])), "given (--known-distance)", 1.0, {}
    if config.marker_size is not None:
        from phirie_jax.frame import markers

        if found:
            scale, band = markers.marker_scale(found, config.marker_size)
            views = max(len(m.views) for m in found)
            if views < markers.GOOD_VIEWS:
                warnings.append(f"--marker-size {config.marker_size:g}: the markers are seen in at most {views} photos "
                                f"(≥ {markers.GOOD_VIEWS} give a scale to about 1 %): the scale is within ×/÷{band:.3g}")
            names = ", ".join(f"{m.dictionary} id {m.ident} in {len(m.views)} photos" for m in found)
            return scale, (f"markers (--marker-size {config.marker_size:g}): {names}, side "
                           f"{np.mean([m.side for m in found]):.4g} units"), band, {"markers": len(found)}
        warnings.append(f"--marker-size {config.marker_size:g}: no marker is seen in two photos "
                        f"({config.marker_dictionary or 'any common dictionary'}); the scale is a prior")
    if distance is None:
        raise SceneInputError(scene.root, "scale", "cannot be estimated without Gaussians in front of the "
                              "cameras (expected --scale, --known-distance, --marker-size or --metric)")
    floor = None
    if decision.support is not None:
        floor = priors.find_floor(samples, decision.support, up, scene.cameras, estimate.PLANE_THRESHOLD * distance)
    scale, source, band, measured = priors.scale_prior(decision.support, planes + ([floor] if floor else []), up,
                                                       scene.cameras, orbit, distance)
    return scale, source, band, {**measured, "prior": True, "floor": None if floor is None else floor.as_dict()}


def resolve_frame(scene: SceneInput, config: FrameConfig = FrameConfig()) -> SceneFrame:
    """Up and metres per unit of the capture (given, declared, measured or estimated) as one
    frame, with the support plane and the cues' evidence. ``--known-size`` is applied later
    (``with_known_size``): it needs the observed instances."""
    rng = np.random.default_rng(SEED)
    given = None if config.up_axis is None else (config.up_axis, f"given (--up {config.up})")
    if not scene.cameras:
        up = given[0] if given else np.array([0.0, 0.0, 1.0])
        decision = UpDecision(up, given[1] if given else "default +z (no cameras)", None, (), (), (), {})
        cues, planes, orbit, found, distance, evidence, samples = [], [], None, [], None, {}, np.zeros((0, 3))
    else:
        cues, planes, orbit, found, distance, evidence, samples = _cues(scene, config, rng)
        reference = consensus(cues)[0] if given is None else given[0]
        marker_plane = _marker_plane(found, scene.cameras, reference) if reference is not None else None
        threshold = estimate.PLANE_THRESHOLD * (distance or 1.0)
        decision = decide_up(cues, planes, orbit, marker_plane, threshold, given)
    up = decision.up / np.linalg.norm(decision.up)
    warnings = list(decision.warnings)
    scale, scale_source, uncertainty, scale_evidence = _scale(scene, config, up, decision, planes, orbit, found,
                                                              distance, warnings, samples)
    evidence = {**evidence, **decision.evidence, "scale": scale_evidence}
    rotation = rotation_to_z(up)
    matrix = sim3_matrix(scale, rotation, np.zeros(3))
    if np.allclose(matrix, np.eye(4), atol=1e-12):
        matrix = np.eye(4)
    return SceneFrame(matrix, up, decision.source, scale_source, uncertainty, evidence, decision.support,
                      tuple(warnings))


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
