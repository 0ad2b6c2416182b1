"""Interactive-environment benchmark: frames/s and simulated steps/s; prints one JSON object.

Single environment (MuJoCo C + the JAX renderer) and batched worlds (MJX + the batched
renderer: the background binned and composited once per camera, each world's body-attached
Gaussians merged into the tiles they reach, which alone are composited again), each against
looping the single environment over the same worlds and cameras, measured in the same run.
Compile times are reported apart from run times (first call vs. the median of later calls). Each
batched run also renders world 0's state with the single environment (the same body poses) and
reports the largest pixel difference from the batched image. ``--whole-images`` also times, in
the same run, the batched render that merges and composites every tile of every image (the
reference the changed-tile render replaces).

    python -m experiments.bench_env OUT_DIR [--worlds 1 8 32] [--cameras 4]

OUT_DIR is a `phirie convert` output folder (scene.xml, background.ply, objects/...).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np

from experiments.profiling import traced
from experiments.report import emit
from experiments.timing import timed, timed_steps
from kernels.composite_pallas import PallasSettings
from kernels.raster import RasterConfig
from phirie_jax.interact.batched import BatchedEnvironment, WorldRenderer
from phirie_jax.interact.environment import Environment


def bench_single(env: Environment, cameras: list[int], steps: int, repeats: int) -> dict:
    env.reset()
    t0 = time.perf_counter()
    env.step(steps)
    sim_s = time.perf_counter() - t0
    first, frame = timed(lambda: env.render(cameras[0]).rgb, repeats)
    return {"sim_steps_per_s": round(steps / sim_s, 1), "render_first_s": round(first, 3),
            "render_ms": round(1e3 * frame, 2), "frames_per_s": round(1.0 / frame, 2)}


def bench_batched(env: Environment, worlds: int, cameras: list[int], steps: int, repeats: int,
                  collision: str, max_images: int, loop: bool = True, trace: Path | None = None,
                  pixels_only: bool = False, whole_images: bool = False,
                  compositor_settings: tuple[tuple[int, int, bool], ...] = ()) -> dict:
    t0 = time.perf_counter()
    batch = BatchedEnvironment(env, worlds, collision=collision)
    put_s = time.perf_counter() - t0
    step_first, step_s = timed_steps(batch, steps, repeats)
    frames = worlds * len(cameras)
    result = {
        "worlds": worlds, "cameras": len(cameras), "steps": steps, "collision": collision,
        "colliding_geoms": int(np.sum((batch.mj_model.geom_contype | batch.mj_model.geom_conaffinity) > 0)),
        "put_model_s": round(put_s, 2), "step_compile_s": round(step_first - step_s, 2),
        "world_steps_per_s": round(worlds * steps / step_s, 1),
        "images_per_render_call": max_images, "moving_gaussians": int(env.object_gaussians.num)}
    print(json.dumps(result), file=sys.stderr, flush=True)
    if not pixels_only:  # every output of the renderer, float32 (GBs at thousands of frames)
        render_first, render_s = timed(lambda: batch.render(cameras, max_images=max_images).rgb, repeats)
        result.update(render_compile_s=round(render_first - render_s, 2), frames_per_s=round(frames / render_s, 2))
    # the policy's layout: uint8 NHWC made inside the rendering program, left on the device
    pixels_first, pixels_s = timed(lambda: batch.render(cameras, max_images=max_images, pixels="uint8"),
                                   repeats)
    result.update(uint8_frames_per_s=round(frames / pixels_s, 2),
                  uint8_render_compile_s=round(pixels_first - pixels_s, 2))
    # world 0's body poses in the single environment (as MJX computed them: after a step
    # they are those of the step's start, in both simulators): the same image, to uint8 rounding
    frames_uint8 = batch.render(cameras, max_images=max_images, pixels="uint8")  # the timed program again
    world0 = np.asarray(frames_uint8[0, 0], np.float64) / 255.0
    env.data.xpos[:] = np.asarray(batch.data.xpos[0])
    quats = np.asarray(batch.data.xquat[0], np.float64)
    env.data.xquat[:] = quats / np.linalg.norm(quats, axis=1, keepdims=True)  # float32 in MJX
    single = np.asarray(env.render(cameras[0]).rgb)
    result["max_abs_rgb_diff_world0_vs_single_uint8"] = round(float(np.max(np.abs(world0 - single))), 4)
    renderer = batch._renderer
    result["changed_tiles"] = {"capacities": dataclasses.asdict(renderer.capacities), "retries": renderer.retries}
    for chunk, warps, prefetch in compositor_settings:  # the changed-tile render with other Pallas settings
        config = RasterConfig(pallas=PallasSettings(chunk=chunk, num_warps=warps, prefetch=prefetch))
        other = WorldRenderer(env, config=config, devices=batch.mesh.devices)
        placements = batch.placements()
        other_first, other_s = timed(lambda: other.render(placements, cameras, max_images=max_images,
                                                          pixels="uint8"), repeats)
        result.setdefault("compositor_settings", []).append(
            {"chunk": chunk, "num_warps": warps, "prefetch": prefetch,
             "uint8_frames_per_s": round(frames / other_s, 2),
             "compile_s": round(other_first - other_s, 2), "speedup_over_default": round(pixels_s / other_s, 3)})
    if whole_images:  # the reference: every tile of every image merged and composited, same run
        whole = WorldRenderer(env, devices=batch.mesh.devices, whole_images=True)
        placements = batch.placements()
        whole_first, whole_s = timed(lambda: whole.render(placements, cameras, max_images=max_images,
                                                          pixels="uint8"), repeats)
        reference = np.asarray(whole.render(placements, cameras, max_images=max_images, pixels="uint8"), np.int32)
        difference = np.abs(np.asarray(frames_uint8, np.int32) - reference)
        result["whole_images"] = {
            "uint8_frames_per_s": round(frames / whole_s, 2), "uint8_render_compile_s": round(whole_first - whole_s, 2),
            "speedup_changed_tiles": round(whole_s / pixels_s, 3),
            "max_abs_uint8_difference": int(difference.max()),
            "share_of_pixels_equal": round(float(np.mean(difference == 0)), 6)}
    if trace is not None:
        result["uint8_render_kernels"] = traced(
            lambda: jax.block_until_ready(batch.render(cameras, max_images=max_images, pixels="uint8")), 3, trace)
    if loop:
        result.update(_loop_baseline(env, worlds, cameras, steps, step_s, pixels_s))
    return result


def _loop_baseline(env: Environment, worlds: int, cameras: list[int], steps: int, step_s: float,
                   render_s: float) -> dict:
    """The same work with the single environment in a loop: worlds × steps, worlds × cameras frames
    (render_s: the batched uint8 render's seconds)."""
    env.reset()
    t0 = time.perf_counter()
    for _ in range(worlds):
        env.step(steps)
    loop_step_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(worlds):
        for c in cameras:
            jax.block_until_ready(env.render(c).rgb)
    loop_render_s = time.perf_counter() - t0
    frames = worlds * len(cameras)
    return {"loop_world_steps_per_s": round(worlds * steps / loop_step_s, 1),
            "loop_frames_per_s": round(frames / loop_render_s, 2),
            "speedup_steps_vs_loop": round(loop_step_s / step_s, 2),
            "speedup_frames_vs_loop": round(loop_render_s / render_s, 2)}


def compositor_setting(text: str) -> tuple[int, int, bool]:
    """``CHUNK:WARPS`` or ``CHUNK:WARPS:prefetch`` → (chunk, warps, prefetch)."""
    parts = text.split(":")
    if len(parts) not in (2, 3) or not all(p.isdigit() for p in parts[:2]) or parts[2:] not in ([], ["prefetch"]):
        raise argparse.ArgumentTypeError(f"{text!r} (expected CHUNK:WARPS or CHUNK:WARPS:prefetch, e.g. 8:4:prefetch)")
    return int(parts[0]), int(parts[1]), len(parts) == 3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--worlds", type=int, nargs="+", default=[1, 8])
    parser.add_argument("--cameras", type=int, default=2)
    parser.add_argument("--steps", type=int, default=240, help="simulator steps per timed call")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--width", type=int, default=None, help="render width (default: the cameras')")
    parser.add_argument("--collision", choices=["hull", "parts"], default="hull",
                        help="the batched worlds' collision model (phirie_jax.interact.mjx_model)")
    parser.add_argument("--max-images", type=int, default=256,
                        help="images per batched rasterization call")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    parser.add_argument("--trace", type=Path, default=None,
                        help="profile 3 batched renders of the largest batch here; the JSON gets the time per kernel")
    parser.add_argument("--pixels-only", action="store_true",
                        help="time only the uint8 frames a policy reads, not the float32 RasterOutput as well")
    parser.add_argument("--whole-images", action="store_true",
                        help="also time the uint8 render that merges and composites every tile (the reference)")
    parser.add_argument("--compositor-settings", nargs="*", default=[], type=compositor_setting,
                        metavar="CHUNK:WARPS[:prefetch]",
                        help="also time the uint8 render with these Pallas compositor settings")
    parser.add_argument("--no-loop", action="store_true",
                        help="skip the single-environment loop baseline (minutes at thousands of frames)")
    args = parser.parse_args()

    env = Environment.load(args.out_dir)
    if args.width is not None:
        env.cameras = [c.scaled(args.width / c.width) for c in env.cameras]
    cameras = list(range(min(args.cameras, len(env.cameras))))
    cam = env.cameras[0]
    result = {
        "scene": str(args.out_dir), "backend": jax.default_backend(), "device": str(jax.devices()[0]),
        "jax": jax.__version__, "machine": platform.platform(), "objects": len(env.objects),
        "gaussians": int(env.background.num + env.object_gaussians.num), "image": [cam.width, cam.height],
        "timestep": env.timestep,
        "single": bench_single(env, cameras, 10 * args.steps, args.repeats),
        "batched": [],
    }
    print(json.dumps(result["single"]), file=sys.stderr, flush=True)
    for worlds in args.worlds:
        result["batched"].append(bench_batched(env, worlds, cameras, args.steps, args.repeats,
                                               args.collision, args.max_images, loop=not args.no_loop,
                                               trace=args.trace if worlds == max(args.worlds) else None,
                                               pixels_only=args.pixels_only, whole_images=args.whole_images,
                                               compositor_settings=tuple(args.compositor_settings)))
        print(json.dumps(result["batched"][-1]), file=sys.stderr, flush=True)
    emit(result, args.out)


if __name__ == "__main__":
    main()
