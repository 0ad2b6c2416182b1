"""What ``report.html`` costs: its renders through one compiled program against one program per
image size and Gaussian bucket (the straightforward way), each in a fresh process.

    python -m experiments.bench_report OUT_DIR [--out experiments/results/bench_report.json]

For each way, a child process renders the report's images twice: the first pass includes the
renderer's compiles (and the environment's scene composition), the second is the run alone.
``shared`` is ``report.renders.render_images`` (every image at the views' size, the capture padded
to the converted scene's Gaussian count); ``separate`` renders the same images with thumbnails at
their own size and the capture in its own bucket. JSON: wall seconds per pass, the cold pass's
render programs and its programs of any kind (eager joins and paddings of a new size included)
with their compile seconds, images, images per second of the warm pass, and the ratio of the
cold passes.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from experiments.report import emit


def _separate(out_dir: Path, views: int, width: int, thumbnail: int) -> int:
    """The report's images, one program per image size and bucket; returns the image count."""
    import numpy as np

    from phirie_jax.interact.environment import Environment
    from phirie_jax.render import render
    from phirie_jax.report.renders import box_corners, crop_camera, source_gaussians, view_cameras

    env = Environment.load(out_dir)
    scene = env.gaussians()
    picks = [env.cameras[k] for k in view_cameras(env.cameras, views)]
    picks = [c if c.width <= width else c.scaled(width / c.width) for c in picks]
    source = source_gaussians(out_dir)
    count = 0
    for camera in picks:
        if source is not None:
            np.asarray(render(source.to_kernel(), camera).rgb)
            count += 1
        np.asarray(render(scene, camera).rgb)
        count += 1
    means = np.asarray(scene.means)
    for o in env.objects:
        rows = slice(env.background.num + o.gaussians.start, env.background.num + o.gaussians.stop)
        crops = [c for c in (crop_camera(cam, box_corners(means[rows]), thumbnail, thumbnail) for cam in env.cameras)
                 if c is not None]
        if crops:
            np.asarray(render(scene, max(crops, key=lambda c: c[1])[0]).rgb)
            count += 1
    return count


def _child(out_dir: Path, way: str, views: int, width: int, thumbnail: int) -> dict:
    from phirie_jax.compile_count import CompileCount
    from phirie_jax.render import TRACE_COUNTS
    from phirie_jax.report.renders import render_images

    def once() -> tuple[float, int]:
        start = time.perf_counter()
        if way == "shared":
            images = render_images(out_dir, views, width, thumbnail, (1.0, 1.0, 1.0))
            count = sum(i is not None for i in images.before) + len(images.after) + len(images.thumbnails)
        else:
            count = _separate(out_dir, views, width, thumbnail)
        return time.perf_counter() - start, count

    with CompileCount() as compiles:
        cold_s, count = once()
    traces = TRACE_COUNTS["render"]
    warm_s, _ = once()
    return {"way": way, "images": count, "cold_s": round(cold_s, 3), "warm_s": round(warm_s, 3),
            "render_programs_compiled": traces, "programs_compiled": compiles.count,
            "compile_s": round(compiles.seconds, 3), "images_per_s_warm": round(count / warm_s, 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", type=Path, help="a converted folder (phirie convert's output)")
    parser.add_argument("--views", type=int, default=3)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--thumbnail", type=int, default=96)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--child", choices=("shared", "separate"), default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(_child(args.out_dir, args.child, args.views, args.width, args.thumbnail)))
        return
    rows = {}
    for way in ("shared", "separate"):  # each in a fresh process: the cold pass compiles from nothing
        command = [sys.executable, "-m", "experiments.bench_report", str(args.out_dir), "--child", way,
                   "--views", str(args.views), "--width", str(args.width), "--thumbnail", str(args.thumbnail)]
        done = subprocess.run(command, capture_output=True, text=True, check=True)
        rows[way] = json.loads(done.stdout.strip().splitlines()[-1])
    emit({"benchmark": "report", "folder": str(args.out_dir), "rows": rows,
          "cold_ratio_separate_over_shared": round(rows["separate"]["cold_s"] / rows["shared"]["cold_s"], 2)},
         args.out)


if __name__ == "__main__":
    main()
