"""CoACD per object under several profiles: parts, hull-volume / mesh-volume ratio, CPU seconds
and the drop-test verdict of the parts as the physics stage writes them; prints one JSON object.

    python -m experiments.coacd_parts --outputs /tmp/crowded/out /tmp/default/out --synthetic \\
        --workers 2 --out experiments/results/coacd_parts.json
    python -m experiments.coacd_parts --outputs out/demo/convert --synthetic --workers 2 \\
        --profiles coacd_merge adaptive --baseline coacd_merge --out experiments/results/coacd_merge.json

Objects: every kept object of each ``--outputs`` folder (a conversion past its objects stage: the
completed meshes the physics stage decomposes, their poses and categories), and with
``--synthetic`` the synthetic categories' own meshes (``--seeds`` each) and an annulus. Profiles:
``fixed`` (``AdaptiveCoacd(enabled=False)`` and CoACD's own merge: threshold 0.05, 60 tree-search
iterations, the repaired mesh of ≤ 40K triangles), ``coacd_merge`` (the settings adapted to each
object's size and complexity, ``collision.coacd_settings``, with CoACD's own merge),
``resolution_2000`` (the default but for CoACD's own concavity sampling, 2000), ``concave_0.1`` /
``concave_0.13`` (the default but for the concave objects' threshold floor,
``AdaptiveCoacd.concave_threshold``, by default the base threshold 0.05) and ``adaptive``
(the default ``PhysicsConfig``: adapted settings, ``collision.merge_parts``). Each
object is built in a worker process with one OpenMP thread (as the physics stage's workers run
with one worker per core), so its CPU seconds are its time on one core. The guard: for every
object, each profile's ratio within ``RATIO_BOUND`` of the ``--baseline`` one and the same
drop-test verdict.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from experiments.report import emit

RATIO_BOUND = 0.1   # |profile − baseline| hull-volume ratio, per object
PROFILES = ("fixed", "coacd_merge", "resolution_2000", "concave_0.1", "concave_0.13", "adaptive")


def profile_config(name: str):
    from phirie_jax.construct.physics.config import AdaptiveCoacd, CoacdConfig, DropTestConfig, PhysicsConfig

    adaptive = AdaptiveCoacd(enabled=name != "fixed")
    if name == "resolution_2000":
        adaptive = AdaptiveCoacd(resolution=CoacdConfig.resolution)
    if name.startswith("concave_"):
        adaptive = AdaptiveCoacd(concave_threshold=float(name.partition("_")[2]))
    merge = "coacd" if name in ("fixed", "coacd_merge") else "volume"
    return PhysicsConfig(coacd=CoacdConfig(adaptive=adaptive, merge=merge), drop_test=DropTestConfig(backend="mujoco"))


def _start(threads: int) -> None:
    os.environ["OMP_NUM_THREADS"] = str(threads)


def build(item: dict, profile: str) -> dict:
    """(In a worker.) One object's collision with one profile, its parts written and read back as
    the physics stage does, and their drop test (MuJoCo C)."""
    from phirie_jax.construct.physics import droptest
    from phirie_jax.construct.physics.body import object_body
    from phirie_jax.construct.physics.collision import collision_from_mesh
    from phirie_jax.construct.physics.parts import read_part, write_parts
    from phirie_jax.construct.physics.priors import Shape, priors
    from phirie_jax.geometry import split_sim3

    config = profile_config(profile)
    vertices, faces = np.asarray(item["vertices"]), np.asarray(item["faces"])
    pose = np.asarray(item["pose"], np.float64)
    cpu, wall = time.process_time(), time.perf_counter()
    col = collision_from_mesh(vertices, faces, config)
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    r = col.report
    with tempfile.TemporaryDirectory() as tmp:
        paths = write_parts(Path(tmp), 1, col.parts)
        parts = [read_part(Path(tmp) / p) for p in paths]
    shape = Shape.of_mesh(vertices, faces, split_sim3(pose)[0])
    body = object_body(1, parts, pose, priors(item["category"], config, shape, 1))
    drop = droptest.drop_test([droptest.drop_body(body, item["up"])], config.drop_test)[0]
    return {"source": item["source"], "object": item["object"], "category": item["category"], "profile": profile,
            "triangles": r["repair"]["triangles"], **{k: r["coacd"][k] for k in ("tier", "solidity", "extent_m",
                                                                                  "threshold", "max_triangles")},
            "method": r["method"], "parts": r["parts"], "max_hull_vertices": max(r["hull_vertices"]),
            "hull_volume_ratio": round(r["hull_volume_ratio"], 4), "cpu_s": round(cpu, 2), "wall_s": round(wall, 2),
            "stable": drop.stable, "drift_m": None if drop.drift_m is None else round(drop.drift_m, 5),
            "drop_error": drop.error}


def output_items(folder: Path) -> list[dict]:
    """The kept objects of a conversion's output folder: canonical mesh, pose, category, up."""
    from phirie_jax.construct.physics.stage import _load_mesh
    from phirie_jax.layout import resolve
    from phirie_jax.manifest import Manifest

    manifest = Manifest.load(folder)
    manifest.objects()   # the objects stage ran
    categories = manifest.categories()
    items = []
    for entry in manifest.kept_objects():
        if not entry.mesh or entry.pose is None:
            continue
        vertices, faces = _load_mesh(resolve(folder, entry.mesh))
        items.append({"source": str(folder), "object": entry.id, "category": categories.get(entry.id),
                      "vertices": vertices, "faces": faces, "pose": entry.pose.tolist(), "up": manifest.up().tolist()})
    return items


def synthetic_items(seeds: int) -> list[dict]:
    import trimesh

    from phirie_jax.synthetic import shapes

    annulus = trimesh.creation.annulus(0.03, 0.05, 0.02, sections=48)
    items = [{"source": "synthetic", "object": "annulus", "category": None, "vertices": annulus.vertices,
              "faces": annulus.faces}]
    for category in shapes.CATEGORIES:
        for seed in range(seeds):
            mesh = shapes.make_object(category, np.random.default_rng(seed), seed).mesh
            items.append({"source": "synthetic", "object": f"{category}_{seed}", "category": category,
                          "vertices": mesh.vertices, "faces": mesh.faces})
    for item in items:
        item.update(pose=np.eye(4).tolist(), up=[0.0, 0.0, 1.0])
    return items


def guard(rows: list[dict], baseline: str, profile: str) -> dict:
    """Per object ``profile`` against ``baseline``: ratio change, verdicts, CPU seconds."""
    pairs = {}
    for r in rows:
        pairs.setdefault((r["source"], r["object"]), {})[r["profile"]] = r
    changes, changed_verdicts, objects = [], [], []
    for (source, obj), p in pairs.items():
        if baseline not in p or profile not in p:
            continue
        delta = p[profile]["hull_volume_ratio"] - p[baseline]["hull_volume_ratio"]
        changes.append(abs(delta))
        if p[profile]["stable"] != p[baseline]["stable"]:
            changed_verdicts.append({"source": source, "object": obj})
        objects.append({"source": source, "object": obj, "ratio_change": round(delta, 4),
                        "cpu_s": [p[baseline]["cpu_s"], p[profile]["cpu_s"]],
                        "parts": [p[baseline]["parts"], p[profile]["parts"]]})
    return {"baseline": baseline, "profile": profile,
            "ratio_bound": RATIO_BOUND, "max_ratio_change": round(max(changes, default=0.0), 4),
            "ratio_within_bound": all(c <= RATIO_BOUND for c in changes),
            "verdicts_unchanged": not changed_verdicts, "changed_verdicts": changed_verdicts, "objects": objects}


def summary(rows: list[dict]) -> dict:
    out = {}
    for profile in PROFILES:
        sel = [r for r in rows if r["profile"] == profile]
        if not sel:
            continue
        out[profile] = {"objects": len(sel), "cpu_s_total": round(sum(r["cpu_s"] for r in sel), 1),
                        "cpu_s_max": max(r["cpu_s"] for r in sel),
                        "cpu_s_median": statistics.median(r["cpu_s"] for r in sel),
                        "parts_total": sum(r["parts"] for r in sel),
                        "stable": sum(bool(r["stable"]) for r in sel)}
        for source in dict.fromkeys(r["source"] for r in sel):
            part = [r for r in sel if r["source"] == source]
            out[profile][source] = {"cpu_s_total": round(sum(r["cpu_s"] for r in part), 1),
                                    "cpu_s_max": max(r["cpu_s"] for r in part)}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--outputs", type=Path, nargs="*", default=[], help="conversion output folders")
    parser.add_argument("--synthetic", action="store_true", help="also the synthetic categories and an annulus")
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--workers", type=int, default=1, help="worker processes (one OpenMP thread each)")
    parser.add_argument("--profiles", nargs="+", default=["fixed", "adaptive"], choices=PROFILES,
                        help="fixed: CoACD's settings and merge; coacd_merge: the adaptive settings with CoACD's "
                             "merge; resolution_2000: the default at CoACD's sampling resolution; concave_T: the "
                             "default with the concave objects' threshold floor T; adaptive: the "
                             "default (adaptive settings, collision.merge_parts)")
    parser.add_argument("--baseline", choices=PROFILES, default="fixed", help="what the guard compares against")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()

    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    items = [i for folder in args.outputs for i in output_items(folder)]
    items += synthetic_items(args.seeds) if args.synthetic else []
    jobs = [(i, p) for i in items for p in args.profiles]
    rows = []
    with ProcessPoolExecutor(args.workers, mp_context=multiprocessing.get_context("spawn"), initializer=_start,
                             initargs=(1,)) as pool:
        for row in pool.map(build, *zip(*jobs)):
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
    fixed, adaptive = profile_config("fixed"), profile_config("adaptive")
    emit({"host": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
          "load_average_at_end": os.getloadavg(), "workers": args.workers, "omp_threads_per_worker": 1,
          "config": {"threshold": fixed.coacd.threshold, "max_parts": fixed.max_parts,
                     "max_hull_vertices": fixed.max_hull_vertices, "resolution": fixed.coacd.resolution,
                     "fixed_mcts_iterations": fixed.coacd.mcts_iterations,
                     "adaptive": dataclasses.asdict(adaptive.coacd.adaptive)},
          "summary": summary(rows),
          "guard": {p: guard(rows, args.baseline, p) for p in args.profiles if p != args.baseline},
          "rows": rows}, args.out)


if __name__ == "__main__":
    main()
