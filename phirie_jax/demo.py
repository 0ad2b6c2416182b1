"""The whole job on the embedded default scene (``make demo``).

1. synthesize the default tabletop (a capture with ground truth, written like a real one);
2. convert it: observe → objects → physics (collision, MJCF/URDF, drop tests) → background;
3. load the interactive environment, shoot the largest object and render the rollout to a
   video, with stills before / after conversion / after the shot;
4. put the Franka Panda beside the table (when ``gymnasium-robotics`` is installed): pick and
   place every object the gripper fits and the arm reaches, and film the first from a scene
   camera and the wrist camera (``ROBOT_FPS``, ``ROBOT_WIDTH``: a short, small clip);
5. print what was converted, how well (against the ground truth) and how long each stage took,
   and write ``report.html`` beside the converted scene (its rollout included).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from phirie_jax.manifest import Manifest
from phirie_jax.progress import task
from phirie_jax.synthetic.scene import write_png

PREVIEW_VIEWS = 4
ROBOT_FPS = 2.0          # the pick-and-place clip: frames per simulated second ...
ROBOT_WIDTH = 160        # ... and the scene camera's width (the wrist camera is 160×120)
ROBOT_SPACING = 0.01     # m between the robot's Gaussians (a light robot for the CPU demo)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(1.0 / mse)


def write_previews(scene_dir: Path, out_dir: Path, background, views: int = PREVIEW_VIEWS) -> list[dict]:
    """Render the loaded scene at ``views`` evenly spread cameras; save render | ground truth."""
    import cv2

    from phirie_jax.io.scene import load_scene
    from phirie_jax.render import prepared, render

    scene = load_scene(scene_dir)
    gaussians = prepared(scene.require_gaussians().to_host_kernel())
    picks = np.linspace(0, len(scene.cameras) - 1, views).round().astype(int)
    rows = []
    for k in picks:
        cam = scene.cameras[k]
        out = render(gaussians, cam, background=np.asarray(background, np.float32))
        rendered = np.asarray(out.rgb)
        truth = cv2.imread(str(cam.image_path), cv2.IMREAD_COLOR)[..., ::-1] / 255.0
        write_png(out_dir / f"preview_{k:04d}.png", np.concatenate([rendered, truth], axis=1))
        rows.append({"camera": int(k), "name": cam.name, "psnr_db": round(psnr(rendered, truth), 2)})
    return rows


def placement_errors(manifest: Manifest, scene_dir: Path) -> dict[int, float]:
    """Per kept object: distance (m) between its placed base centre and the true object's."""
    truth = {o["id"]: np.asarray(o["pose"]) for o in json.loads((scene_dir / "gt" / "objects.json").read_text())}
    return {obj.id: float(np.linalg.norm(obj.pose[:3, 3] - truth[obj.id][:3, 3]))
            for obj in manifest.kept_objects() if obj.id in truth}


def background_scores(truth, convert_dir: Path, manifest: Manifest, camera, background_rgb) -> dict:
    """PSNR of the background stage's result against the truth (objects gone, hidden tabletop
    included; ``truth``: ``synthetic.truth.background_truth``) in one view: inside the region the
    objects covered, with the fill and with the removal alone, and outside it."""
    from phirie_jax.io.ply import read_gaussian_ply
    from phirie_jax.render import render
    from phirie_jax.synthetic.truth import uncovered_region

    region = uncovered_region(truth, camera, background_rgb)
    result = read_gaussian_ply(convert_dir / manifest.background().path)
    removal_only = result.subset(np.arange(result.num - manifest.background().filled))
    bg = np.asarray(background_rgb, np.float32)
    images = {name: np.asarray(render(g.to_kernel(), camera, background=bg).rgb)
              for name, g in (("truth", truth.truth), ("filled", result), ("removal_only", removal_only))}

    def masked_psnr(image, mask):
        return psnr(image[mask], images["truth"][mask])

    return {"region_px": int(region.sum()), "uncovered": float(masked_psnr(images["filled"], region)),
            "uncovered_removal_only": float(masked_psnr(images["removal_only"], region)),
            "outside": float(masked_psnr(images["filled"], ~region))}


def run_demo(out: Path, preset: str = "default", seed: int = 0) -> dict:
    """Steps 1–5 of the module docstring, their progress shown (``progress.display_for``); ends by
    printing the path of the converted folder's ``report.html``."""
    from rich.console import Console

    from phirie_jax.progress import display_for, showing

    console = Console()
    with showing(display_for(console)):
        result = _run(out, preset, seed, console)
    console.print(f"report: {result['report']}")
    return result


def _run(out: Path, preset: str, seed: int, console) -> dict:
    from phirie_jax.interact.environment import Environment
    from phirie_jax.interact.rollout import RolloutConfig, rollout, write_video
    from phirie_jax.pipeline import run_convert
    from phirie_jax.render import render
    from phirie_jax.report.page import write_report
    from phirie_jax.synthetic import synthesize
    from phirie_jax.synthetic.truth import background_truth

    timings: dict[str, float] = {}
    scene_dir, convert_dir, media = out / "scene", out / "convert", out / "media"

    def timed(name, fn, total=None):
        t0 = time.perf_counter()
        with task(name, total) as status:
            result = fn(status)
        timings[name] = time.perf_counter() - t0
        return result

    scene = timed("synthesize", lambda s: synthesize(scene_dir, preset=preset, seed=seed))
    bg = scene.config.background_rgb
    previews = timed("previews", lambda s: write_previews(scene_dir, media, bg))
    timed("convert", lambda s: run_convert(scene_dir, convert_dir, progress=lambda stage: s.update(f"convert: {stage}")))
    manifest = Manifest.load(convert_dir)
    env = Environment.load(convert_dir)
    rollout_config = RolloutConfig(background=bg)
    truth = background_truth(scene_dir)  # the capture, its labels and the scene without objects
    captured = np.asarray(render(truth.capture.to_kernel(), env.camera(rollout_config.camera),
                                 background=np.asarray(bg, np.float32)).rgb)
    result = timed("rollout", lambda s: rollout(env, rollout_config, on_frame=lambda i: s()),
                   total=rollout_config.frames)
    write_video(media / "rollout.mp4", result["frames"], rollout_config.fps)
    report = timed("report", lambda s: write_report(convert_dir, video=media / "rollout.mp4",
                                                    frames=result["frames"]))
    write_png(media / "before.png", captured)
    write_png(media / "after_conversion.png", result["frames"][0] / 255.0)
    write_png(media / "after_shot.png", result["frames"][-1] / 255.0)

    robot = timed("robot", lambda s: robot_rollouts(convert_dir, media, bg, s))
    scores = (background_scores(truth, convert_dir, manifest, env.camera(rollout_config.camera), bg)
              if manifest.background() is not None and manifest.background().path else None)
    table = _summary_table(out, scene, scene_dir, convert_dir, media, manifest, result, previews, scores,
                           rollout_config.camera, {**timings, **_stage_timings(manifest)})
    for row in robot["rows"]:
        table.add_row(f"pick-place object {row['object']}", _robot_row(row))
    if robot.get("skipped"):
        table.add_row("robot", robot["skipped"])
    console.print(table)
    return {"timings": timings, "previews": previews, "manifest": manifest.data, "background_scores": scores,
            "robot": robot, "report": report}


def robot_rollouts(convert_dir: Path, media: Path, background, status) -> dict:
    """Step 4 of the module docstring: every object's scripted pick-and-place, and the first
    success (else the first attempt) filmed to ``media/pick_place.mp4``."""
    from phirie_jax.errors import SceneInputError
    from phirie_jax.interact.environment import Environment
    from phirie_jax.interact.robot.config import RobotConfig
    from phirie_jax.interact.rollout import PickPlaceRolloutConfig, pick_place_each, pick_place_rollout, write_video

    try:
        env = Environment.load(convert_dir, robot=RobotConfig(spacing=ROBOT_SPACING))
    except SceneInputError as err:  # e.g. gymnasium-robotics not installed
        return {"rows": [], "skipped": str(err)}
    status.update("robot: pick-and-place of each object")
    rows = pick_place_each(env)
    tried = [r for r in rows if "success" in r and "goal" in r]
    if not tried:
        return {"rows": rows, "placement": env.robot.placement.record()}
    chosen = next((r for r in tried if r["success"]), tried[0])
    config = PickPlaceRolloutConfig(fps=ROBOT_FPS, width=ROBOT_WIDTH, background=tuple(background))
    clip = pick_place_rollout(env, chosen["object"], chosen["goal"], config,
                              on_frame=lambda i: status.update(f"robot: frame {i + 1}"))
    write_video(media / "pick_place.mp4", clip["frames"], config.fps)
    write_png(media / "pick_place.png", clip["frames"][len(clip["frames"]) // 2] / 255.0)
    return {"rows": rows, "placement": env.robot.placement.record(), "video": str(media / "pick_place.mp4"),
            "filmed": clip["outcome"]}


def _robot_row(row: dict) -> str:
    if row.get("mounted"):
        return row["reason"]
    if not row["fits"]:
        return f"does not fit the gripper (narrowest width {100 * row['width_m']:.1f} cm)"
    if not row["reachable"]:
        return "out of the arm's reach"
    if "distance_m" not in row:
        return row.get("reason", "not tried")
    return (f"{'success' if row['success'] else 'missed'}: {100 * row['distance_m']:.1f} cm from the goal, "
            f"tilted {row['tilt_deg']:.1f}°")


def _summary_table(out: Path, scene, scene_dir: Path, convert_dir: Path, media: Path, manifest: Manifest, result: dict,
                   previews: list[dict], scores: dict | None, camera: int, timings: dict[str, float]):
    """What was converted, how well (against the synthetic truth) and how long it took."""
    from rich.table import Table

    from phirie_jax.info import candidate_name

    table = Table(title=f"phirie demo → {out}")
    table.add_column("what")
    table.add_column("value")
    table.add_row("scene", f"{scene_dir} ({len(scene.cameras)} cameras {scene.config.width}×{scene.config.height}, "
                           f"{scene.capture.data.num:,} Gaussians)")
    table.add_row("true objects", ", ".join(f"{o.id}:{o.shape.category}" for o in scene.objects))
    table.add_row("instances observed", str(len(manifest.get("instances", ()))))
    errors = placement_errors(manifest, scene_dir)
    for obj in manifest.get("objects", ()):
        drop = obj.drop_test or {}
        failed = obj.failed_checks
        table.add_row(f"object {obj.id}", f"{obj.status} · candidate {candidate_name(obj)} · placed "
                      f"{100 * errors.get(obj.id, float('nan')):.1f} cm from truth · drop test "
                      f"{'stable' if drop.get('stable') else 'unstable' if drop else '—'}"
                      + (f" · failed checks {failed}" if failed else ""))
    background = manifest.background()
    table.add_row("background", "—" if background is None else
                  f"{background.removed} Gaussians removed, {background.filled} filled")
    if scores is not None:
        table.add_row("background vs truth", f"camera {camera}: uncovered region "
                      f"({scores['region_px']} px) {scores['uncovered']:.1f} dB PSNR (removal alone "
                      f"{scores['uncovered_removal_only']:.1f} dB), elsewhere {scores['outside']:.1f} dB")
    table.add_row("shot", f"object {result['shot'].get('hit')} moved "
                          f"{100 * result['moved_m'].get(result['shot'].get('hit'), 0.0):.1f} cm")
    for row in previews:
        table.add_row(f"re-render {row['name']}", f"{row['psnr_db']} dB PSNR against the written image")
    for stage, seconds in timings.items():
        table.add_row(f"time: {stage}", f"{seconds:.1f} s")
    table.add_row("outputs", f"{convert_dir} (scene.xml, manifest.json, objects/, background.ply), "
                             f"{media} (rollout.mp4, before/after stills, previews)")
    return table


def _stage_timings(manifest: Manifest) -> dict[str, float]:
    """The conversion's own top-level stage timings (``observe``, ``objects``, ...)."""
    return {f"  {k}": float(v) for k, v in manifest.timings.values.items() if "." not in k and k != "convert"}
