"""``phirie convert-many`` on this machine's CPUs: 3 tiny scenes with 1 worker against 2 workers,
and the same scenes converted one after the other by ``phirie convert`` (the baseline).

    python -m experiments.bench_convert_many --work /tmp/bench_convert_many \\
        --out experiments/results/convert_many_cpu.json

Each run is a child process (its own local Ray instance), timed from start to exit, so Ray's start
and each scene's worker start are in it. The scenes are the ``tiny`` preset (seeds 3, 4, 5), the
conversions the test suite's cheap ones (no background refinement, no report). The per-scene
seconds and peak memory are the tasks' own (``summary.json``); the load average before and after
each run says how busy the machine was (other work on it slows every run). ``--repeats`` runs
each setting that many times in turn and reports each run.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

CHEAP = ["--config.background.refine.iterations", "0", "--config.report.no-enabled"]
SEEDS = (3, 4, 5)


def scenes(work: Path) -> list[Path]:
    from phirie_jax.synthetic import synthesize

    found = []
    for seed in SEEDS:
        scene = work / "scenes" / f"tiny{seed}"
        if not (scene / "point_cloud.ply").is_file():
            synthesize(scene, preset="tiny", seed=seed)
        found.append(scene)
    return found


def timed(command: list[str]) -> tuple[float, list[float], list[float]]:
    """(wall seconds, load averages before, after) of a child process; raises when it fails."""
    before = list(os.getloadavg())
    start = time.perf_counter()
    done = subprocess.run(command, check=False, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} exited {done.returncode}:\n{done.stderr[-3000:]}")
    return round(seconds, 2), [round(v, 2) for v in before], [round(v, 2) for v in os.getloadavg()]


def many(scene_dirs: list[Path], root: Path, workers: int) -> dict:
    shutil.rmtree(root, ignore_errors=True)
    seconds, before, after = timed([sys.executable, "-m", "phirie_jax.cli", "convert-many", *map(str, scene_dirs),
                                    "--out", str(root), "--workers", str(workers), *CHEAP])
    summary = json.loads((root / "summary.json").read_text())
    return {"workers": workers, "wall_s": seconds, "load_before": before, "load_after": after,
            "statuses": [r["status"] for r in summary["scenes"]],
            "scene_s": [r["seconds"] for r in summary["scenes"]],
            "peak_memory_mb": [r["peak_memory_mb"] for r in summary["scenes"]]}


def alone(scene_dirs: list[Path], root: Path) -> dict:
    shutil.rmtree(root, ignore_errors=True)
    runs = [timed([sys.executable, "-m", "phirie_jax.cli", "convert", str(s), "--out", str(root / s.name), *CHEAP])
            for s in scene_dirs]
    return {"wall_s": round(sum(r[0] for r in runs), 2), "scene_s": [r[0] for r in runs],
            "load_before": runs[0][1], "load_after": runs[-1][2]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=Path("/tmp/bench_convert_many"))
    parser.add_argument("--out", type=Path, default=None, help="write the JSON here too")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--commit", default=None, help="the code's commit (default: git rev-parse HEAD)")
    parser.add_argument("--no-alone", action="store_true", help="leave out the one-after-the-other baseline")
    args = parser.parse_args()
    import ray

    scene_dirs = scenes(args.work)
    runs: dict[str, list[dict]] = {"workers_1": [], "workers_2": [], "alone": []}
    for _ in range(args.repeats):
        runs["workers_1"].append(many(scene_dirs, args.work / "many1", 1))
        runs["workers_2"].append(many(scene_dirs, args.work / "many2", 2))
        if not args.no_alone:
            runs["alone"].append(alone(scene_dirs, args.work / "alone"))
    best = {k: min(r["wall_s"] for r in v) for k, v in runs.items() if v}
    commit = args.commit or subprocess.run(["git", "rev-parse", "HEAD"], check=False, capture_output=True, text=True,
                                           cwd=Path(__file__).resolve().parents[1]).stdout.strip() or None
    result = {
        "what": "3 tiny synthetic scenes (seeds 3, 4, 5), cheap conversions (no refinement, no report)",
        "commit": commit,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
                    "ray": ray.__version__},
        "best_wall_s": best,
        "speedup_2_over_1": round(best["workers_1"] / best["workers_2"], 3),
        "runs": runs,
    }
    text = json.dumps(result, indent=2)
    print(text)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
