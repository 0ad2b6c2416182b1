"""The background stage alone on a converted folder: wall and CPU seconds of each step, the XLA
programs it compiled and its crop renders; prints one JSON object.

    python -m experiments.bench_background --capture /tmp/crowded/capture --objects /tmp/crowded/out \\
        --work /tmp/bench_background --out experiments/results/bench_background_crowded_cpu.json

``--objects`` is a conversion's output past its objects stage (``convert_scale.py`` writes one;
``--resume`` runs leave it so); it is copied to ``--work`` and the background stage run there as the
pipeline runs it (``run_convert(..., stages=("background",))``: the frame is decided again, then
the background). CPU seconds are the process's (every thread), so they say what a step costs on a
shared machine better than its wall time; the XLA compilations are counted per step (on a GPU
each costs tens of milliseconds, and a count that grows with the objects is a cost per object). The script imports only what every version of the stage
has, so the same file measures an older checkout on ``PYTHONPATH`` (the before of a change).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import shutil
import time
from pathlib import Path

from experiments.report import emit

COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--capture", type=Path, required=True, help="the scene folder the conversion read")
    parser.add_argument("--objects", type=Path, required=True, help="its output folder, past the objects stage")
    parser.add_argument("--work", type=Path, default=Path("/tmp/bench_background"))
    parser.add_argument("--label", default=None, help="what this run measures (e.g. the commit)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()

    import jax

    from phirie_jax.manifest import Manifest, Timings
    from phirie_jax.pipeline import run_convert

    compiles = {"count": 0, "seconds": 0.0}
    step_compiles: dict[str, dict] = {}
    active: list[str] = []

    def listener(event, duration, **_):
        if event == COMPILE_EVENT:
            for record in [compiles] + [step_compiles.setdefault(n, {"count": 0, "seconds": 0.0}) for n in active]:
                record["count"] += 1
                record["seconds"] += duration

    jax.monitoring.register_event_duration_secs_listener(listener)
    cpu: dict[str, float] = {}
    timed = Timings.timed

    @contextlib.contextmanager
    def timed_with_cpu(self, name):
        start = time.process_time()
        active.append(name)
        try:
            with timed(self, name):
                yield
        finally:
            active.remove(name)
        cpu[name] = cpu.get(name, 0.0) + time.process_time() - start

    Timings.timed = timed_with_cpu
    shutil.rmtree(args.work, ignore_errors=True)
    shutil.copytree(args.objects, args.work, ignore=shutil.ignore_patterns("background*"))
    start = time.perf_counter()
    run_convert(args.capture, args.work, masks="auto", stages=("background",), allow_outside_paths=True)
    wall = time.perf_counter() - start
    manifest = Manifest.load(args.work)
    b = manifest.background()
    kept = [o for o in b.objects if o["status"] not in ("skipped", "failed")]
    steps = {k: v for k, v in manifest.timings.values.items() if k.startswith("background")}
    emit({"label": args.label, "phirie_jax": str(Path(__import__("phirie_jax").__file__).parent),
          "machine": {"platform": platform.platform(), "jax_backend": jax.default_backend(), "cpus": os.cpu_count(),
                      "load_average_at_end": os.getloadavg()},
          "objects": len(kept), "gaussians": b.source_gaussians, "wall_s": round(wall, 1),
          "step_s": {k: round(v, 2) for k, v in steps.items()},
          "step_cpu_s": {k: round(v, 2) for k, v in cpu.items() if k.startswith("background")},
          "per_object_s": {k: round(v / max(len(kept), 1), 3) for k, v in steps.items()},
          "compiles": {"count": compiles["count"], "seconds": round(compiles["seconds"], 2)},
          "step_compiles": {k: {"count": v["count"], "seconds": round(v["seconds"], 2)}
                            for k, v in step_compiles.items() if k.startswith("background")},
          "renders": b.extra.get("renders"), "render_launches": b.extra.get("render_launches"),
          "frames": len((b.extra.get("targets") or {}).get("frames") or []),
          "removed": b.removed, "filled": b.filled,
          "statuses": {s: sum(o["status"] == s for o in b.objects) for s in {o["status"] for o in b.objects}}},
         args.out)


if __name__ == "__main__":
    main()
