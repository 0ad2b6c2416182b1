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

from phirie_jax.construct.physics.body import is_mounted
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


@dataclasses.dataclass(frozen=True)
class PickPlaceRolloutConfig:
    """A rendered pick-and-place (``phirie simulate --robot panda --task pick-place``).

    Attributes:
        fps: frames per second of simulated time (and of the video).
        camera: scene camera index (None: the capture camera that sees the object, the goal and
            the robot's base, from across the robot).
        width: render width of the scene camera in pixels (None: the camera's).
        background: colour behind the scene, rgb in [0, 1].
    """

    fps: float = 12.0
    camera: int | None = None
    width: int | None = None
    background: tuple[float, float, float] = (0.62, 0.66, 0.72)

    def __post_init__(self):
        check_ranges(self, {"fps": POSITIVE, "camera": NON_NEGATIVE, "width": AT_LEAST_ONE,
                            "background": Each(FRACTION, count=3)})


def robot_view(env: Environment, points: np.ndarray) -> int:
    """The capture camera that sees the most of ``points`` (P, 3), farthest from the robot's base
    among those (it looks at the arm's front)."""
    base = env.robot.placement.base.position
    best, best_key = 0, None
    for k, cam in enumerate(env.cameras):
        uv, depth = cam.project(np.asarray(points, np.float64))
        seen = int(np.sum((depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0)
                          & (uv[:, 1] < cam.height)))
        key = (seen, float(np.linalg.norm(cam.center[:2] - base[:2])))
        if best_key is None or key > best_key:
            best, best_key = k, key
    return best


def free_goal(env: Environment, object_id: int, distance: float = 0.15) -> np.ndarray:
    """A goal (x, y) ``distance`` from the object on its support, clear of the other objects and
    reachable (the first of eight directions, sideways to the robot first, whose plan succeeds)."""
    from phirie_jax.interact.robot import script

    grasp = script.grasp_for(env, object_id)
    base = env.robot.placement.base.position
    towards = (base[:2] - grasp.centre[:2]) / np.linalg.norm(base[:2] - grasp.centre[:2])
    sideways = np.array([-towards[1], towards[0]])
    others = [script.grasp_for(env, o.id).centre[:2] for o in env.objects if o.id not in (None, object_id)]
    for angle in np.radians([0, 180, 45, 135, -45, -135, 90, -90]):
        c, s = np.cos(angle), np.sin(angle)
        goal = grasp.centre[:2] + distance * (c * sideways + s * towards)
        if any(np.linalg.norm(goal - o) < distance * 0.8 for o in others):
            continue
        try:
            script.plan_pick_place(env, object_id, goal)
        except script.UnreachableError:
            continue
        return goal
    raise script.UnreachableError(f"no free, reachable goal {100 * distance:.0f} cm from object {object_id}")


def pick_place_rollout(env: Environment, object_id: int, goal, config: PickPlaceRolloutConfig = PickPlaceRolloutConfig(),
                       on_frame=None) -> dict:
    """Plan and run the scripted pick-and-place, rendering the scene camera and the wrist camera
    side by side at ``fps``. Returns the frames (uint8), the outcome and the plan's segments."""
    from phirie_jax.interact.robot import script

    env.reset()
    plan = script.plan_pick_place(env, object_id, goal)
    body = env.object(object_id).body_id
    start_rotation = env.data.xmat[body].reshape(3, 3).copy()
    grasp = script.grasp_for(env, object_id)
    camera = config.camera if config.camera is not None else robot_view(
        env, np.array([grasp.centre, [*np.asarray(goal)[:2], grasp.centre[2]], env.robot.placement.base.position]))
    every = max(1, int(round(plan.hz / config.fps)))
    frames = []

    def frame(tick: int) -> None:
        if tick % every:
            return
        scene = to_uint8(env.render(camera, background=config.background, width=config.width).rgb)
        views = [scene]
        if env.robot.camera is not None:
            wrist = to_uint8(env.render("wrist", background=config.background).rgb)
            views.append(_fit_height(wrist, scene.shape[0]))
        frames.append(np.concatenate(views, axis=1))
        if on_frame is not None:
            on_frame(len(frames) - 1)

    frame(0)
    script.run_plan(env, plan, on_tick=lambda tick: frame(tick + 1))
    result = script.outcome(env, object_id, goal, start_rotation)
    return {"frames": frames, "outcome": result, "camera": camera, "segments": plan.segments,
            "simulated_s": plan.seconds}


def _fit_height(image: np.ndarray, height: int) -> np.ndarray:
    import cv2

    width = int(round(image.shape[1] * height / image.shape[0]))
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)


def simulate_pick_place(out_dir, out: Path, robot: str, base, object_id: int | None, goal, camera: int | None,
                        width: int | None, fps: float | None) -> dict:
    """``phirie simulate --task pick-place``: load with the robot, pick the object (default: the
    first reachable one the gripper fits), place it at ``goal`` (default ``free_goal``), write
    the video. A task the robot cannot do is one ``OptionError`` line naming the option."""
    from phirie_jax.errors import ConfigValueError, OptionError
    from phirie_jax.interact.robot import script
    from phirie_jax.interact.robot.config import RobotConfig

    try:
        robot_config = RobotConfig(model=robot, base=base)
        config = PickPlaceRolloutConfig(**{k: v for k, v in (("fps", fps), ("camera", camera), ("width", width))
                                           if v is not None})
    except ConfigValueError as err:
        raise OptionError("--" + err.field.replace("_", "-"), f"expected {err.expected}", err.shown) from None
    env = Environment.load(out_dir, robot=robot_config)
    if object_id is None:
        fits = [o.id for o in env.objects if o.id in env.robot.placement.reachable and script.grasp_for(env, o.id).fits]
        if not fits:
            raise OptionError("--object", "no object both fits the gripper and is within the arm's reach "
                                          f"(reachable: {list(env.robot.placement.reachable)})")
        object_id = fits[0]
    try:
        env.object(object_id)
    except KeyError:
        raise OptionError("--object", f"expected one of {[o.id for o in env.objects if o.id is not None]}",
                          str(object_id)) from None
    try:
        goal = free_goal(env, object_id) if goal is None else np.asarray(goal, np.float64)
        result = pick_place_rollout(env, object_id, goal, config)
    except script.UnreachableError as err:
        option = "--object" if "does not fit" in str(err) else "--to"
        raise OptionError(option, str(err)) from None
    write_video(out, result["frames"], config.fps)
    return result


def pick_place_each(env: Environment, distance: float = 0.15) -> list[dict]:
    """The scripted pick-and-place of every object from the initial state (no rendering): each
    row says whether it fits the gripper, is in reach, and the outcome towards ``free_goal``
    (a mounted object, welded to its wall, is not picked: its row says so)."""
    from phirie_jax.interact.robot import script

    rows = []
    for o in [o for o in env.objects if o.id is not None]:
        if is_mounted(env.model, o.body):
            rows.append({"object": o.id, "mounted": True, "success": False,
                         "reason": "mounted: welded to its wall, it is not picked"})
            continue
        env.reset()
        grasp = script.grasp_for(env, o.id)
        row = {"object": o.id, "width_m": grasp.width, "fits": bool(grasp.fits),
               "reachable": o.id in env.robot.placement.reachable}
        if grasp.fits and row["reachable"]:
            start_rotation = env.data.xmat[o.body_id].reshape(3, 3).copy()
            try:
                goal = free_goal(env, o.id, distance)
                script.run_plan(env, script.plan_pick_place(env, o.id, goal))
                row.update(script.outcome(env, o.id, goal, start_rotation))
            except script.UnreachableError as err:
                row.update(success=False, reason=str(err))
        rows.append(row)
    env.reset()
    return rows
