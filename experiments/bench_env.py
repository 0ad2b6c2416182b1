"""Interactive-environment benchmark: frames/s and simulated steps/s; prints one JSON object.

Single environment (MuJoCo C + the JAX renderer) and batched worlds (MJX + one
worlds × cameras rasterization), each against looping the single environment over the
same worlds and cameras, measured in the same run. Compile times are reported apart from
run times (first call vs. the median of later calls).

    python -m experiments.bench_env OUT_DIR [--worlds 1 8 32] [--cameras 4]

OUT_DIR is a `phirie convert` output folder (scene.xml, background.ply, objects/...).
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from pathlib import Path

import jax
import numpy as np

from phirie_jax.interact.batched import BatchedEnvironment  # noqa: E402
from phirie_jax.interact.environment import Environment  # noqa: E402


def timed(fn, repeats: int) -> tuple[float, float]:
    """(first call s, median of ``repeats`` later calls s); results are blocked on."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return first, statistics.median(times)


def bench_single(env: Environment, cameras: list[int], steps: int, repeats: int) -> dict:
    env.reset()
    t0 = time.perf_counter()
    env.step(steps)
    sim_s = time.perf_counter() - t0
    first, frame = timed(lambda: env.render(cameras[0]).rgb, repeats)
    return {"sim_steps_per_s": round(steps / sim_s, 1), "render_first_s": round(first, 3),
            "render_ms": round(1e3 * frame, 2), "frames_per_s": round(1.0 / frame, 2)}


def bench_batched(env: Environment, worlds: int, cameras: list[int], steps: int, repeats: int,
                  collision: str) -> dict:
    t0 = time.perf_counter()
    batch = BatchedEnvironment(env, worlds, collision=collision)
    put_s = time.perf_counter() - t0
    step_first, step_s = timed(lambda: (batch.step(steps), batch.data.qpos)[1], repeats)
    render_first, render_s = timed(lambda: batch.render(cameras).rgb, repeats)
    # the same work with the single environment in a loop: worlds × steps, worlds × cameras frames
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
    return {
        "worlds": worlds, "cameras": len(cameras), "steps": steps, "collision": collision,
        "colliding_geoms": int(np.sum((batch.mj_model.geom_contype | batch.mj_model.geom_conaffinity) > 0)),
        "put_model_s": round(put_s, 2),
        "step_compile_s": round(step_first - step_s, 2), "render_compile_s": round(render_first - render_s, 2),
        "world_steps_per_s": round(worlds * steps / step_s, 1),
        "frames_per_s": round(frames / render_s, 2),
        "loop_world_steps_per_s": round(worlds * steps / loop_step_s, 1),
        "loop_frames_per_s": round(frames / loop_render_s, 2),
        "speedup_steps_vs_loop": round(loop_step_s / step_s, 2),
        "speedup_frames_vs_loop": round(loop_render_s / render_s, 2),
    }


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
        result["batched"].append(bench_batched(env, worlds, cameras, args.steps, args.repeats, args.collision))
        print(json.dumps(result["batched"][-1]), file=sys.stderr, flush=True)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
