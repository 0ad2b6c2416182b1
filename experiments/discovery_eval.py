"""Automatic discovery, end to end: which movable bodies ``--masks auto`` makes on a capture
without a scan, masks or candidates, against the synthetic truth.

    python -m experiments.discovery_eval --preset default --seeds 2001 2002 2003 \
        --variants ideal artefacts fitted fitted+artefacts [--gsplat DIR ...] \
        --scene-root /tmp/phirie_scenes --work /tmp/discovery_eval --out experiments/results/discovery_eval.json
    # real captures (no truth: the supports, clusters, instances and objects auto discovery makes)
    python -m experiments.discovery_eval --variants --real ../shared/data/captures/snowmiku --out ...

Scenes: the synthetic ``--preset`` of each seed (``--scene-root/<preset><seed>``, synthesized when
missing); ``fitted``: its Gaussians fitted by the project's own fitter (``phirie synth --fitted``,
``FIT_PRESETS``); ``artefacts``: what gsplat's densification leaves (``synthetic.artefacts``: four
1–2 cm floor bumps and four floater clouds added to the capture); ``--gsplat DIR``: scene folders
whose Gaussians gsplat fitted (``experiments/fit_gsplat.py``, each holds gt/). Each is linked
without ``surface.ply``, ``masks/`` and ``candidates/``, as a user's capture comes, and converted
with ``--masks auto`` through ``--stages`` (observe → objects by default; the surface is
splat-derived). Its ``frame.json`` (metric, +z up) is kept: the frame estimate is measured apart.

Scores per scene (issue 14's definition), on the objects the run keeps (status ``accepted`` or
``unverified``): a kept object matches a true object when the F1@20 mm of its placed mesh against
the true world mesh is ≥ 0.9, one to one, greedily by F1. TP = matched, FP = kept objects matching
none (phantoms; ``on_artefact``: those within 5 cm of an added bump or floater), FN = true objects
unmatched; precision = TP / (TP + FP), recall = TP / (TP + FN). Beside it, the same matching at
F1@40 mm ≥ 0.5 (``located``), and the observation alone: instances against the true objects'
visible surfaces at 3D IoU ≥ 0.5 (``observe.evaluate``).
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import time
from pathlib import Path

import numpy as np

from phirie_jax.manifest import Manifest

F1_MATCH = 0.9       # issue 14: an accepted object matching no true object at F1@20 ≥ 0.9 is a phantom
LOCATED_F1_40 = 0.5  # the friendlier column: F1@40 ≥ 0.5
LEFT_OUT = ("surface.ply", "masks", "candidates")
ON_ARTEFACT = 0.05   # m: a phantom this close (horizontally) to an added artefact is on it


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
    return {"tp": len(strict), "fp": accepted - len(strict), "fn": truths - len(strict),
            "objects": truths, "accepted": accepted, "matched": len(strict),
            "recall": round(len(strict) / max(truths, 1), 4),
            "precision": round(len(strict) / accepted, 4) if accepted else None,
            "phantoms": accepted - len(strict),
            "located": len(located), "located_recall": round(len(located) / max(truths, 1), 4),
            "located_precision": round(len(located) / accepted, 4) if accepted else None,
            "matches": [(int(g), int(p)) for g, p, _ in strict]}


def _artefacts(scene_dir: Path) -> list[dict]:
    path = scene_dir / "gt" / "artefacts.json"
    return json.loads(path.read_text())["artefacts"] if path.exists() else []


def evaluate_scene(scene_dir: Path, work: Path, metrics, stages: tuple[str, ...]) -> dict:
    import trimesh

    from phirie_jax.observe.evaluate import evaluate
    from phirie_jax.pipeline import run_convert

    capture = user_capture(scene_dir, work / "capture")
    out = work / "out"
    if out.exists():
        shutil.rmtree(out)
    t0 = time.perf_counter()
    error = None
    try:
        run_convert(capture, out, masks="auto", stages=stages, allow_outside_paths=True)
    except Exception as err:  # noqa: BLE001 — a failed conversion is a row of the table, not the end of the run
        error = f"{type(err).__name__}: {err}"
    wall = time.perf_counter() - t0
    manifest = Manifest.load(out)
    truth = json.loads((scene_dir / "gt" / "objects.json").read_text())
    instances = {i.id: i for i in manifest.get("instances", ())}
    kept = manifest.kept_objects()
    f1_20 = np.zeros((len(truth), len(kept)))
    f1_40 = np.zeros_like(f1_20)
    for p, obj in enumerate(kept):
        mesh = trimesh.load(out / obj.mesh, force="mesh")
        for g, t in enumerate(truth):
            m = metrics(mesh, obj.pose, scene_dir / t["mesh"])
            f1_20[g, p], f1_40[g, p] = m["f1_20"], m["f1_40"]
    result = scores(f1_20, f1_40)
    artefacts = _artefacts(scene_dir)
    per_object = []
    for p, obj in enumerate(kept):
        g = int(np.argmax(f1_20[:, p])) if len(truth) else None
        inst = instances.get(obj.id)
        lo, hi = np.zeros((2, 3)) if inst is None or inst.bounds is None else inst.bounds
        centre = 0.5 * (lo + hi)
        near = [a["kind"] for a in artefacts if np.linalg.norm(np.asarray(a["centre"][:2]) - centre[:2]) < ON_ARTEFACT]
        per_object.append({"id": obj.id, "status": str(obj.status), "candidate": obj.candidate,
                           "views": 0 if inst is None else len(inst.views),
                           "confidence": None if inst is None else inst.confidence,
                           "height_m": round(float(hi[2] - lo[2]), 4),
                           "best_truth": truth[g]["id"] if g is not None else None,
                           "best_f1_20": round(float(f1_20[g, p]), 4) if g is not None else None,
                           "best_f1_40": round(float(f1_40[:, p].max()), 4) if len(truth) else None,
                           "phantom": all(q != p for _, q in result["matches"]), "near_artefact": near,
                           "failed_checks": obj.unresolved_checks or []})
    phantoms = [o for o in per_object if o["phantom"]]
    try:
        observed = evaluate(scene_dir, out)
        observation = {"instances": observed["instances"], "tp": observed["matched"],
                       "fp": observed["instances"] - observed["matched"], "fn": observed["objects"] - observed["matched"],
                       "precision": round(observed["precision"], 4), "recall": round(observed["recall"], 4)}
    except (OSError, KeyError, ValueError) as err:
        observation = {"error": f"{type(err).__name__}: {err}"}
    auto = manifest.get("observe", {}).get("auto", {})
    return {**result, "on_artefact": sum(bool(o["near_artefact"]) for o in phantoms), "artefacts": len(artefacts),
            "instances": len(instances), "observation": observation, "error": error, "wall_s": round(wall, 1),
            "supports": [{k: s[k] for k in ("offset", "area_m2", "source")} for s in auto.get("supports", [])],
            "rejected_clusters": [{k: r.get(k) for k in ("points", "height_m", "views", "looking_views", "reason")}
                                  for r in auto.get("rejected_clusters", []) if r.get("points", 0) >= 40],
            "not_kept": [{"id": o.id, "status": str(o.status), "reason": o.reason}
                         for o in manifest.get("objects", ()) if not o.kept],
            "timings": {k: round(v, 2) for k, v in manifest.timings.values.items() if "." not in k},
            "per_object": per_object}


def real_capture(scene: Path, work: Path, stages: tuple[str, ...]) -> dict:
    """``--masks auto`` on a real capture (no truth): the frame, the supports, what was found and kept."""
    from phirie_jax.pipeline import run_convert

    out = work / "out"
    if out.exists():
        shutil.rmtree(out)
    t0 = time.perf_counter()
    error = None
    try:
        run_convert(scene, out, masks="auto", stages=stages)
    except Exception as err:  # noqa: BLE001 — recorded, as for a synthetic scene
        error = f"{type(err).__name__}: {err}"
    manifest = Manifest.load(out)
    frame, auto = manifest.frame(), (manifest.get("observe") or {}).get("auto", {})
    instances = {i.id: i for i in manifest.get("instances", ())}

    def size(inst):
        lo, hi = inst.bounds
        return (hi - lo).round(3).tolist()

    return {"scene": str(scene), "error": error, "wall_s": round(time.perf_counter() - t0, 1),
            "frame": {k: None if frame is None else getattr(frame, k)
                      for k in ("scale", "up_source", "scale_source", "scale_uncertainty")},
            "frame_support": auto.get("frame_support"), "samples": auto.get("samples"),
            "supports": auto.get("supports"), "support_planes": auto.get("support_planes"),
            "clusters": [{k: o.get(k) for k in ("id", "points", "extent_m", "height_m", "views", "looking_views",
                                                "centroid")} for o in auto.get("objects", [])],
            "rejected_clusters": [{k: r.get(k) for k in ("points", "height_m", "views", "looking_views", "reason")}
                                  for r in auto.get("rejected_clusters", []) if r.get("points", 0) >= 40],
            "instances": [{"id": i.id, "views": len(i.views), "confidence": i.confidence,
                           "points": i.num_points, "size_m": size(i)} for i in instances.values()],
            "rejected_instances": [r for r in manifest.get("observe", {}).get("rejected_proposals", [])
                                   if "instance" in r],
            "objects": [{"id": o.id, "status": str(o.status), "candidate": o.candidate,
                         "reason": o.reason, "failed_checks": o.unresolved_checks or []}
                        for o in manifest.get("objects", ())],
            "timings": {k: round(v, 2) for k, v in manifest.timings.values.items() if "." not in k}}


def summarize(rows: list[dict]) -> dict:
    total = {k: sum(r[k] for r in rows) for k in ("tp", "fp", "fn", "objects", "accepted", "located", "on_artefact")}
    obs = [r["observation"] for r in rows if "tp" in r["observation"]]
    observed = {k: sum(o[k] for o in obs) for k in ("tp", "fp", "fn")}
    return {**total, "recall": round(total["tp"] / max(total["tp"] + total["fn"], 1), 4),
            "precision": round(total["tp"] / (total["tp"] + total["fp"]), 4) if total["tp"] + total["fp"] else None,
            "located_recall": round(total["located"] / max(total["objects"], 1), 4),
            "located_precision": round(total["located"] / total["accepted"], 4) if total["accepted"] else None,
            "observation": {**observed, "recall": round(observed["tp"] / max(observed["tp"] + observed["fn"], 1), 4),
                            "precision": (round(observed["tp"] / (observed["tp"] + observed["fp"]), 4)
                                          if observed["tp"] + observed["fp"] else None)},
            "failed_conversions": sum(r["error"] is not None for r in rows),
            "wall_s_mean": round(float(np.mean([r["wall_s"] for r in rows])), 1)}


def scene_folder(root: Path, preset: str, seed: int, variant: str) -> Path:
    """The folder of one (preset, seed, variant): synthesized, fitted and given artefacts as named."""
    from phirie_jax.synthetic.artefacts import add_artefacts
    from phirie_jax.synthetic.fitted import ensure_synthesized

    fitted = variant.startswith("fitted")
    base = ensure_synthesized(root / f"{preset}{seed}{'_fitted' if fitted else ''}", preset, seed, fitted)
    if not variant.endswith("artefacts"):
        return base
    path = root / f"{base.name}_artefacts"
    if not (path / "gt" / "artefacts.json").exists():
        if path.exists():
            shutil.rmtree(path)
        shutil.copytree(base, path)
        add_artefacts(path, seed)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="default")
    parser.add_argument("--seeds", type=int, nargs="+", default=[2001, 2002, 2003])
    parser.add_argument("--variants", nargs="*", default=["ideal", "artefacts"],
                        choices=["ideal", "artefacts", "fitted", "fitted+artefacts"])
    parser.add_argument("--gsplat", type=Path, nargs="*", default=[], help="gsplat-fitted scene folders (gt/ kept)")
    parser.add_argument("--real", type=Path, nargs="*", default=[],
                        help="real captures (no truth): what auto discovery finds and keeps")
    parser.add_argument("--stages", nargs="+", default=["observe", "objects"])
    parser.add_argument("--scene-root", type=Path, default=Path("/tmp/phirie_scenes"))
    parser.add_argument("--work", type=Path, default=Path("/tmp/discovery_eval"))
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()

    from experiments.objects_eval import Metrics
    from experiments.report import emit

    metrics = Metrics()
    result = {"what": __doc__.split("\n\n")[2].strip(), "f1_match": F1_MATCH, "located_f1_40": LOCATED_F1_40,
              "preset": args.preset, "seeds": args.seeds, "stages": args.stages,
              "machine": {"platform": platform.platform(), "cpus": __import__("os").cpu_count()}}
    runs = [(variant, [(seed, lambda seed=seed, v=variant: scene_folder(args.scene_root, args.preset, seed, v))
                       for seed in args.seeds]) for variant in args.variants]
    if args.gsplat:
        runs.append(("gsplat", [(path.name, lambda path=path: path) for path in args.gsplat]))
    if args.real:
        result["real"] = []
        for scene in args.real:
            result["real"].append(real_capture(scene, args.work / f"real_{scene.name}", tuple(args.stages)))
            print(json.dumps({k: result["real"][-1][k] for k in ("scene", "error", "wall_s", "objects")}), flush=True)
    for name, scenes in runs:
        rows = []
        for seed, make in scenes:
            scene = make()
            row = {"seed": seed, "scene": str(scene),
                   **evaluate_scene(scene, args.work / f"{name}_{seed}", metrics, tuple(args.stages))}
            print(json.dumps({k: row[k] for k in ("seed", "tp", "fp", "fn", "precision", "recall", "on_artefact",
                                                  "observation", "error", "wall_s")}), flush=True)
            rows.append(row)
        result[name] = {"summary": summarize(rows), "scenes": rows}
    emit(result, args.out)


if __name__ == "__main__":
    main()
