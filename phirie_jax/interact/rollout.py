"""Rollouts rendered to video: what ``phirie simulate`` and the demo run.

The default interaction shoots the largest object: an impulse along the ray through the
pixel where its centre appears, so it leaves its support and the filled background shows.
Frames are rendered from the simulator's poses at ``fps``; the video is written to a
temporary name and renamed.
"""

from __future__ import annotations

import dataclasses
import os
import tempfile
from pathlib import Path

import numpy as np

from phirie_jax.interact.environment import Environment
from phirie_jax.ranges import AT_LEAST_ONE, FRACTION, NON_NEGATIVE, POSITIVE, Each, Range, check_ranges


@dataclasses.dataclass(frozen=True)
class RolloutConfig:
    """A rendered rollout.

    Attributes:
        frames: frames rendered after the shot.
        fps: frames per second of simulated time (and of the video).
        camera: camera index the video is rendered from.
        width: render width in pixels (None: the camera's).
        speed: the shot gives the hit object this speed (m/s) along the ray.
        shoot_at: pixel (u, v) to shoot through; None = the largest object's centre.
        background: colour behind the scene, rgb in [0, 1].
    """

    frames: int = 48
    fps: float = 24.0
    camera: int = 0
    width: int | None = None
    speed: float = 2.5
    shoot_at: tuple[float, float] | None = None
    background: tuple[float, float, float] = (0.62, 0.66, 0.72)

    def __post_init__(self):
        check_ranges(self, {"frames": AT_LEAST_ONE, "fps": POSITIVE, "camera": NON_NEGATIVE, "width": AT_LEAST_ONE,
                            "speed": NON_NEGATIVE, "shoot_at": Each(Range(), count=2),
                            "background": Each(FRACTION, count=3)})


def largest_object(env: Environment) -> int | None:
    """Id of the object whose Gaussians span the largest box (None without objects)."""
    best, size = None, -1.0
    for o in env.objects:
        if o.id is None:  # a robot link
            continue
        means = np.asarray(env.object_gaussians.means[o.gaussians])
        extent = float(np.prod(means.max(0) - means.min(0) + 1e-6)) if len(means) else 0.0
        if extent > size:
            best, size = o.id, extent
    return best


def object_pixel(env: Environment, object_id: int, camera: int) -> tuple[float, float] | None:
    """Where the centre of an object's Gaussians appears in a camera (None when off-screen)."""
    o = env.object(object_id)
    placement = env.placements()[env.objects.index(o)]
    means = np.asarray(env.object_gaussians.means[o.gaussians], np.float64)
    centre = placement[:3, :3] @ (0.5 * (means.min(0) + means.max(0))) + placement[:3, 3]
    cam = env.camera(camera)
    uv, depth = cam.project(centre[None])
    if depth[0] <= 0 or not (0 <= uv[0, 0] < cam.width and 0 <= uv[0, 1] < cam.height):
        return None
    return float(uv[0, 0]), float(uv[0, 1])


def to_uint8(rgb) -> np.ndarray:
    return np.clip(np.round(np.asarray(rgb) * 255.0), 0, 255).astype(np.uint8)


def write_video(path: Path, frames: list[np.ndarray], fps: float) -> None:
    """MP4 (mp4v) of uint8 RGB frames, written to a temporary name and renamed."""
    import cv2

    from phirie_jax.io.atomic import ordinary_file_mode

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix or ".mp4", dir=path.parent)
    os.close(fd)
    try:
        height, width = frames[0].shape[:2]
        writer = cv2.VideoWriter(tmp, cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (width, height))
        if not writer.isOpened():
            raise RuntimeError(f"OpenCV cannot write MP4 video to {path}")
        for frame in frames:
            writer.write(frame[..., ::-1])
        writer.release()
        os.chmod(tmp, ordinary_file_mode())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def rollout(env: Environment, config: RolloutConfig = RolloutConfig(), on_frame=None) -> dict:
    """Shoot, simulate and render. Returns the frames (uint8) and what happened."""
    steps_per_frame = max(1, int(round(1.0 / (config.fps * env.timestep))))
    pixel = config.shoot_at
    target = None
    if pixel is None:
        target = largest_object(env)
        pixel = None if target is None else object_pixel(env, target, config.camera)
    first = to_uint8(env.render(config.camera, background=config.background, width=config.width).rgb)
    shot = env.shoot(config.camera, pixel, speed=config.speed) if pixel is not None else {"hit": None}
    frames = [first]
    start = {o.id: env.placements()[i][:3, 3].copy() for i, o in enumerate(env.objects) if o.id is not None}
    for i in range(config.frames):
        env.step(steps_per_frame)
        frames.append(to_uint8(env.render(config.camera, background=config.background, width=config.width).rgb))
        if on_frame is not None:
            on_frame(i)
    moved = {o.id: float(np.linalg.norm(env.placements()[i][:3, 3] - start[o.id]))
             for i, o in enumerate(env.objects) if o.id is not None}
    return {"frames": frames, "shot": shot, "target": target, "pixel": pixel, "moved_m": moved,
            "simulated_s": config.frames * steps_per_frame * env.timestep}
