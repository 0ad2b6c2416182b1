"""Automatic discovery, end to end: which movable bodies ``--masks auto`` makes on a capture
without a scan, masks or candidates, against the synthetic truth.

    python -m experiments.discovery_eval --seeds 2001 2002 2003 2004 [--fitted] \\
        --scene-root /tmp/phirie_scenes --work /tmp/discovery_eval --out experiments/results/discovery_eval.json

Each synthetic ``default`` scene (``--scene-root/eval<seed>``, synthesized when missing; with
``--fitted`` also ``eval<seed>_fitted``, its Gaussians fitted to its images — see
``experiments/fit_scenes.py``) is linked without ``surface.ply``, ``masks/`` and
``candidates/``, as a user's capture comes, and converted with ``--masks auto`` through the
physics stage (observe → objects → physics; the surface is splat-derived). Its ``frame.json``
(metric, +z up) is kept: the frame estimate is measured apart (``tests/frame/``).

Scores (issue 14's definition): an accepted object matches a true object when the F1@20 mm of
its placed mesh against the true world mesh is ≥ 0.9; objects and true objects are matched one
to one, greedily by F1. An accepted object that matches none is a *phantom*. Recall = matched true
objects / true objects; precision = matched accepted objects / accepted objects. Beside it, the
same matching at F1@40 mm ≥ 0.5 (``located``: the body is where a true object is, whatever its
shape quality), and per object its best F1@20 / F1@40, its candidate and the instance's views.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

F1_MATCH = 0.9       # issue 14: an accepted object matching no true object at F1@20 ≥ 0.9 is a phantom
LOCATED_F1_40 = 0.5  # the friendlier column: F1@40 ≥ 0.5
LEFT_OUT = ("surface.ply", "masks", "candidates")


def user_capture(src: Path, dst: Path, leave_out: tuple[str, ...] = LEFT_OUT) -> Path:
    """``dst``: ``src`` as a user's capture comes (symlinks to all but ``leave_out``: by default no
    scan mesh, masks or candidates)."""
    import shutil

    if dst.exists():
        shutil.rmtree(dst)
    dst.mkdir(parents=True)
    for entry in src.iterdir():
        if entry.name not in leave_out:
            (dst / entry.name).symlink_to(entry.resolve())
    return dst


def scores(f1_20: np.ndarray, f1_40: np.ndarray) -> dict:
    """Recall / precision from (true objects × accepted objects) F1 matrices (module docstring)."""
    from phirie_jax.observe.evaluate import match

    truths, accepted = f1_20.shape
    strict, located = match(f1_20, F1_MATCH), match(f1_40, LOCATED_F1_40)
    return {"objects": truths, "accepted": accepted, "matched": len(strict),
            "recall": round(len(strict) / max(truths, 1), 4),
            "precision": round(len(strict) / accepted, 4) if accepted else None,
            "phantoms": accepted - len(strict),
            "located": len(located), "located_recall": round(len(located) / max(truths, 1), 4),
            "located_precision": round(len(located) / accepted, 4) if accepted else None,
            "matches": [(int(g), int(p)) for g, p, _ in strict]}


def evaluate_scene(scene_dir: Path, work: Path, metrics) -> dict:
    import trimesh

    from phirie_jax.pipeline import run_convert

    capture = user_capture(scene_dir, work / "capture")
    out = work / "out"
    t0 = time.perf_counter()
    error = None
    try:
        run_convert(capture, out, masks="auto", stages=("observe", "objects", "physics"))
    except Exception as err:  # noqa: BLE001 — a failed conversion is a row of the table, not the end of the run
        error = f"{type(err).__name__}: {err}"
    wall = time.perf_counter() - t0
    manifest = json.loads((out / "manifest.json").read_text())
    truth = json.loads((scene_dir / "gt" / "objects.json").read_text())
    instances = {i["id"]: i for i in manifest.get("instances", [])}
    accepted = [o for o in manifest.get("objects", []) if o.get("status") == "accepted"]
    f1_20 = np.zeros((len(truth), len(accepted)))
    f1_40 = np.zeros_like(f1_20)
    for p, obj in enumerate(accepted):
        mesh = trimesh.load(out / obj["mesh"], force="mesh")
        for g, t in enumerate(truth):
            m = metrics(mesh, obj["pose"], scene_dir / t["mesh"])
            f1_20[g, p], f1_40[g, p] = m["f1_20"], m["f1_40"]
    result = scores(f1_20, f1_40)
    per_object = []
    for p, obj in enumerate(accepted):
        g = int(np.argmax(f1_20[:, p])) if len(truth) else None
        inst = instances.get(obj["id"], {})
        lo, hi = (np.asarray(b) for b in inst.get("bounds", [[0, 0, 0], [0, 0, 0]]))
        per_object.append({"id": obj["id"], "candidate": obj.get("candidate"), "views": len(inst.get("views", [])),
                           "height_m": round(float(hi[2] - lo[2]), 4),
                           "best_truth": truth[g]["id"] if g is not None else None,
                           "best_f1_20": round(float(f1_20[g, p]), 4) if g is not None else None,
                           "best_f1_40": round(float(f1_40[:, p].max()), 4) if len(truth) else None,
                           "phantom": all(q != p for _, q in result["matches"])})
    return {**result, "instances": len(instances), "error": error, "wall_s": round(wall, 1),
            "rejected_objects": [{"id": o["id"], "reason": o.get("reason")} for o in manifest.get("objects", [])
                                 if o.get("status") != "accepted"],
            "timings": {k: round(v, 2) for k, v in manifest.get("timings", {}).items() if "." not in k},
            "per_object": per_object}


def summarize(rows: list[dict]) -> dict:
    total = {k: sum(r[k] for r in rows) for k in ("objects", "accepted", "matched", "phantoms", "located")}
    return {**total, "recall": round(total["matched"] / max(total["objects"], 1), 4),
            "precision": round(total["matched"] / total["accepted"], 4) if total["accepted"] else None,
            "located_recall": round(total["located"] / max(total["objects"], 1), 4),
            "located_precision": round(total["located"] / total["accepted"], 4) if total["accepted"] else None,
            "failed_conversions": sum(r["error"] is not None for r in rows),
            "wall_s_mean": round(float(np.mean([r["wall_s"] for r in rows])), 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[2001, 2002, 2003, 2004])
    parser.add_argument("--scene-root", type=Path, default=Path("/tmp/phirie_scenes"))
    parser.add_argument("--work", type=Path, default=Path("/tmp/discovery_eval"))
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--fitted", action="store_true", help="also every scene with fitted Gaussians")
    args = parser.parse_args()

    from experiments.objects_eval import Metrics
    from experiments.report import emit
    from phirie_jax.synthetic.fitted import ensure_synthesized

    metrics = Metrics()
    variants = [("ideal", False)] + ([("fitted", True)] if args.fitted else [])
    result = {"what": __doc__.split("\n\n")[2].strip(), "f1_match": F1_MATCH, "located_f1_40": LOCATED_F1_40,
              "seeds": args.seeds, "machine": {"platform": platform.platform(), "cpus": __import__("os").cpu_count()}}
    for name, fitted in variants:
        rows = []
        for seed in args.seeds:
            scene = ensure_synthesized(args.scene_root / (f"eval{seed}_fitted" if fitted else f"eval{seed}"),
                                       "default", seed, fitted)
            row = {"seed": seed, **evaluate_scene(scene, args.work / f"{name}{seed}", metrics)}
            print(json.dumps({k: v for k, v in row.items() if k not in ("per_object", "matches")}), flush=True)
            rows.append(row)
        result[name] = {"summary": summarize(rows), "scenes": rows}
    emit(result, args.out)


if __name__ == "__main__":
    main()
