"""The background branch on synthetic scenes, against the true background (hidden tabletop included).

    python -m experiments.background_eval --seeds 7001 7002 7003 --scene-root /tmp/bg_eval/scenes \\
        --work /tmp/bg_eval/work --out experiments/results/background_eval.json

Per seed: the ``default`` scene is synthesized (if missing), observed (mask files, scan mesh) and
its objects constructed with the default configs; then ``run_background`` runs once per variant:

    exemplar   exemplar (patch-copy) targets, the disks refined (the default)
    telea      OpenCV Telea targets, refined
    ns         Navier–Stokes targets, refined
    init       exemplar targets, the disks only initialized from them (no refinement)

and everything is rendered at 320×240 from held-out cameras (``HELD_OUT`` views on rings between
and above the capture's, never used by any stage), over the scene's background colour:

    truth            gt/background.ply ∪ the capture's floaters (the capture's label-0 Gaussians that
                     are not in gt/background.ply): the scene as it should be with the objects gone
    removal only     G0 \\ ∪R_i (the holes left as they are)
    2D inpaint       removal only, then each held-out image inpainted in 2D (exemplar / Telea / NS) inside the
                     same hole definition as the targets — no 3D fill, no consistency between views
    fill (init)      the ``init`` variant's background.ply
    fill (refined)   the refined variants' background.ply

Uncovered region of a view: pixels where the capture's object Gaussians (gt labels > 0) carry a
composited weight ≥ ``REGION_WEIGHT``. PSNR and SSIM (11×11 Gaussian window) inside it, PSNR
outside it (there the result should be the truth: collateral removal shows up here), and PSNR /
SSIM on the *hidden* pixels alone: where the truth shows tabletop that no capture Gaussian had
(weight ≥ ``HIDDEN_WEIGHT``) — the part only a completion can get right. (The synthetic table's
underside carries the same wood pattern as its top, 4 cm below, so "removal only" sees a shifted
copy of the right texture through the hole: a stronger baseline than a real capture gives.) Ghosts:
object Gaussians left in background.ply (``gt/labels.npy`` > 0), per object with their opacity;
collateral: background Gaussians removed.

Uncovered region, worst view (issue 15's metric): from every capture camera, the pixels where the
capture's own render differs visibly from the true background's (mean absolute RGB difference
> ``VISIBLE_CHANGE`` on [0, 1]); PSNR of each result against the truth over those pixels, for the
worst view and the mean over views (``uncovered``).
With ``--fitted`` every seed is evaluated a second time on the same scene with its Gaussians fitted
to the images (``phirie synth --fitted``, under ``--scene-root/bg<seed>_fitted``): G0 is then the
fitted set, labelled by the nearest ideal Gaussian (``gt/labels.npy``); the truth stays the ideal
background (``synthetic.truth`` reads ``gt/ideal/``). Reported as ``fitted`` beside the rest.
Seed 0 was used while developing; report only others.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import time
from pathlib import Path

import numpy as np

from phirie_jax import layout
from phirie_jax.manifest import Manifest
from phirie_jax.synthetic.truth import REGION_WEIGHT, background_truth

DEV_SEEDS = (0,)
HELD_OUT = 12
VISIBLE_CHANGE = 0.08  # a capture-camera pixel is uncovered where capture and truth differ by this much
HIDDEN_WEIGHT = 0.5  # a pixel shows the hidden tabletop where its Gaussians carry this much weight in the truth
# variant → (inpainting method, refinement iterations; None: the default)
VARIANTS = {"exemplar": ("exemplar", None), "telea": ("telea", None), "ns": ("ns", None), "init": ("exemplar", 0)}
DEFAULT_VARIANT = "exemplar"  # the stage's defaults


def _scene(root: Path, seed: int, fit_config=None, candidates: bool = False) -> Path:
    """The seed's ``default`` scene; with ``fit_config`` (a ``FitConfig``) its fitted variant; with
    ``candidates``, external candidates written beside it as ``objects_eval`` writes them."""
    from phirie_jax.synthetic.fitted import ensure_synthesized

    fitted = fit_config is not None
    kwargs = {"config": fit_config} if fitted else {}
    name = f"bg{seed}" + ("_fitted" if fitted else "") + ("_candidates" if candidates else "")
    scene = ensure_synthesized(root / name, "default", seed, fitted, **kwargs)
    if candidates and not (scene / "candidates").is_dir():
        from experiments.objects_eval import synthetic_candidates

        synthetic_candidates(scene, seed)
    return scene


def _objects(scene_dir: Path, out: Path):
    """The folder's manifest once the observation and object stages ran (run now when they did not)."""
    from phirie_jax.construct.objects.config import ObjectsConfig
    from phirie_jax.construct.objects.stage import run_objects
    from phirie_jax.construct.physics.settling import candidate_settler
    from phirie_jax.observe.config import ObserveConfig
    from phirie_jax.observe.stage import run_observe

    if (out / "manifest.json").exists() and Manifest.load(out).get("objects") is not None:
        return Manifest.load(out)
    run_observe(scene_dir, out, ObserveConfig(), masks="files")
    run_objects(scene_dir, out, ObjectsConfig(), settle=candidate_settler())
    return Manifest.load(out)


def held_out_cameras(scene_cameras, seed: int):
    """Cameras on rings between and above the capture's, looking at the table."""
    from phirie_jax.synthetic.scene import look_at
    from phirie_jax.types import Camera

    ref = scene_cameras[0]
    rng = np.random.default_rng(seed + 99)
    cams = []
    for k in range(HELD_OUT):
        radius, height = ((1.1, 1.45), (1.35, 1.2), (0.8, 1.75))[k % 3]
        angle = 2 * np.pi * (k + 0.5) / HELD_OUT + rng.uniform(-0.1, 0.1)
        eye = np.array([radius * np.cos(angle), radius * np.sin(angle), height])
        target = np.array([*rng.uniform(-0.15, 0.15, 2), 0.78])
        cams.append(Camera(f"heldout_{k:02d}", ref.K, look_at(eye, target), ref.width, ref.height))
    return cams


def _render(data, cams, background, features=None):
    import jax.numpy as jnp

    from phirie_jax.render import render

    g = data.to_kernel()
    f = None if features is None else jnp.asarray(features, jnp.float32)
    return [render(g, c, background=background, features=f) for c in cams]


METRICS = ("psnr_in", "ssim_in", "psnr_out", "psnr_hidden", "ssim_hidden")


def _metrics(image, truth, region, hidden) -> dict:
    import jax.numpy as jnp

    from kernels.image_metrics import psnr, ssim

    a, b = jnp.asarray(image, jnp.float32), jnp.asarray(truth, jnp.float32)
    inside, outside, under = jnp.asarray(region), jnp.asarray(~region), jnp.asarray(hidden)
    out = {"psnr_in": float(psnr(a, b, inside)), "ssim_in": float(ssim(a, b, inside)),
           "psnr_out": float(psnr(a, b, outside))}
    if hidden.sum() >= 20:
        out.update(psnr_hidden=float(psnr(a, b, under)), ssim_hidden=float(ssim(a, b, under)))
    return out


def _variant(inpaint: str, iterations: int | None):
    """The ``BackgroundConfig`` of a variant."""
    from phirie_jax.construct.background.config import BackgroundConfig, RefineConfig, TargetsConfig

    refine = RefineConfig() if iterations is None else RefineConfig(iterations=iterations)
    return BackgroundConfig(targets=TargetsConfig(inpaint=inpaint), refine=refine)


def _hole(full_out, kept_out, disk_out, config) -> np.ndarray:
    """The targets' hole definition (``construct.background.targets.finish_frame``) on a full image.
    config: a ``TargetsConfig``."""
    from scipy import ndimage

    region = np.asarray(full_out.features)[..., 0] >= config.region_weight
    region = ndimage.binary_dilation(region, iterations=config.region_dilate_px)
    kept_alpha = np.asarray(kept_out.alpha)
    see_through = np.asarray(kept_out.depth_normalized) > np.asarray(disk_out.depth_normalized) \
        + config.plane_depth_tolerance
    on_disks = np.asarray(disk_out.alpha) >= 0.5
    return region & on_disks & ((kept_alpha < config.explained_alpha) | see_through)


def evaluate_seed(seed: int, scene_root: Path, work: Path, fit_config=None, candidates: bool = False) -> dict:
    from phirie_jax.construct.background.config import BackgroundConfig
    from phirie_jax.construct.background.stage import run_background
    from phirie_jax.construct.background.targets import inpaint
    from phirie_jax.io.ply import read_gaussian_ply
    from phirie_jax.synthetic.scene import PRESETS

    scene_dir = _scene(scene_root, seed, fit_config, candidates)
    work = work / "fitted" if fit_config is not None else work
    work = work / "candidates" if candidates else work
    base = work / f"bg{seed}" / "objects"
    t0 = time.perf_counter()
    manifest = _objects(scene_dir, base)
    objects_s = time.perf_counter() - t0
    results = {"seed": seed, "objects": [{"id": o.id, "status": str(o.status)} for o in manifest.objects()]}
    runs = {}
    for name, (method, iterations) in VARIANTS.items():
        out = work / f"bg{seed}" / name
        shutil.rmtree(out, ignore_errors=True)
        shutil.copytree(base, out)
        t0 = time.perf_counter()
        run_background(scene_dir, out, _variant(method, iterations))
        wall = time.perf_counter() - t0
        m = Manifest.load(out)
        b = m.background()
        runs[name] = (out, b)
        refined = b.extra.get("refine")
        results[f"run_{name}"] = {
            "wall_s": round(wall, 2),
            "timings": {k: v for k, v in m.timings.values.items() if k.startswith("background")},
            "removed": b.removed, "filled": b.filled, "unsupported": list(b.unsupported_regions),
            "failed": list(b.failed_completions), "renders": b.extra.get("renders"),
            "refine": None if refined is None else {k: refined[k] for k in (
                "steps", "loss_initial", "loss_final", "first_call_s", "loop_s", "buckets", "reverted")},
            "per_object": [{k: o.get(k) for k in ("id", "status", "removed", "fill", "primary_view", "reason")}
                           for o in b.objects]}
        print(f"seed {seed} {name}: {wall:.1f} s, removed {b.removed}, filled {b.filled}", flush=True)

    t = background_truth(scene_dir)
    capture, labels, truth, hidden_g = t.capture, t.labels, t.truth, t.hidden
    out0, b0 = runs[DEFAULT_VARIANT]
    result = read_gaussian_ply(out0 / layout.BACKGROUND)
    kept = result.subset(np.arange(result.num - b0.filled))
    from scipy.spatial import cKDTree

    d, _ = cKDTree(kept.means).query(capture.means)
    left = d < 1e-6
    results["ghosts"] = int(np.sum(left & (labels > 0)))
    results["ghosts_per_object"] = ghosts_per_object(left, labels, capture.opacity_logits)
    results["ghost_opacity_sum"] = float(np.sum(1 / (1 + np.exp(-capture.opacity_logits[left & (labels > 0)]))))
    results["collateral"] = int(np.sum(~left & (labels == 0)))
    results["object_gaussians"] = int(np.sum(labels > 0))

    bg = np.asarray(PRESETS["default"].background_rgb, np.float32)
    cams = held_out_cameras(read_scene_cameras(scene_dir), seed)
    removed = ~left
    obj_w = _render(capture, cams, bg, (labels > 0)[:, None].astype(np.float32))
    full = _render(capture, cams, bg, removed[:, None].astype(np.float32))
    truth_r = _render(truth, cams, bg, hidden_g[:, None].astype(np.float32))
    kept_r = _render(kept, cams, bg)
    cfg = BackgroundConfig().targets
    fills = {name: read_gaussian_ply(out / layout.BACKGROUND) for name, (out, _) in runs.items()}
    disks = fills["init"].subset(np.arange(fills["init"].num - runs["init"][1].filled, fills["init"].num))
    disk_r = _render(disks, cams, bg)
    fill_r = {name: _render(data, cams, bg) for name, data in fills.items()}
    rows: dict[str, list[dict]] = {}
    for k in range(len(cams)):
        region = np.asarray(obj_w[k].features)[..., 0] >= REGION_WEIGHT
        if region.sum() < 50:
            continue
        gt = np.asarray(truth_r[k].rgb)
        hidden = np.asarray(truth_r[k].features)[..., 0] >= HIDDEN_WEIGHT
        kept_img = np.asarray(kept_r[k].rgb)
        hole = _hole(full[k], kept_r[k], disk_r[k], cfg)
        entries = {"removal only": kept_img}
        for method in ("exemplar", "telea", "ns"):
            entries[f"removal + 2D inpaint ({method})"] = inpaint(kept_img, hole, method, cfg.inpaint_radius)
        entries["fill, initialized only (exemplar targets)"] = np.asarray(fill_r["init"][k].rgb)
        for method in ("exemplar", "telea", "ns"):
            entries[f"fill, refined ({method} targets)"] = np.asarray(fill_r[method][k].rgb)
        for name, img in entries.items():
            rows.setdefault(name, []).append({"view": k, "region_px": int(region.sum()), "hidden_px": int(hidden.sum()),
                                              **_metrics(img, gt, region, hidden)})
    results["views"] = rows
    capture_cams = read_scene_cameras(scene_dir)
    results["uncovered"] = uncovered_region(
        capture, truth, {"removal only": kept, **{f"fill, refined ({m})": fills[m] for m in ("exemplar", "telea", "ns")},
                         "fill, initialized only (exemplar targets)": fills["init"]}, capture_cams, bg)
    results["summary"] = {name: _mean(vs) for name, vs in rows.items()}
    results["objects_stage_s"] = round(objects_s, 2)
    return results


def ghosts_per_object(left: np.ndarray, labels: np.ndarray, opacity_logits: np.ndarray) -> list[dict]:
    """Per true object: its capture Gaussians still in background.ply and their opacities."""
    out = []
    for k in sorted(int(v) for v in np.unique(labels) if v > 0):
        ghost = left & (labels == k)
        alpha = 1 / (1 + np.exp(-opacity_logits[ghost].astype(np.float64)))
        out.append({"id": k, "ghosts": int(ghost.sum()),
                    "opacity_max": round(float(alpha.max()), 4) if ghost.any() else None,
                    "opacity_sum": round(float(alpha.sum()), 4)})
    return out


def uncovered_region(capture, truth, results: dict, cams, background) -> dict:
    """Issue 15's uncovered-region PSNR (module docstring) of each result in ``results`` (name →
    Gaussian set): per view, then the worst view and the mean over views."""
    from phirie_jax.render import render

    capture_g, truth_g = capture.to_kernel(), truth.to_kernel()
    result_g = {name: data.to_kernel() for name, data in results.items()}
    views: dict[str, list[dict]] = {name: [] for name in results}
    for k, cam in enumerate(cams):
        gt = np.asarray(render(truth_g, cam, background=background).rgb)
        seen = np.asarray(render(capture_g, cam, background=background).rgb)
        region = np.abs(seen - gt).mean(-1) > VISIBLE_CHANGE
        if region.sum() < 20:
            continue
        for name, g in result_g.items():
            img = np.asarray(render(g, cam, background=background).rgb)
            mse = float(np.mean((img[region] - gt[region]) ** 2))
            views[name].append({"view": k, "region_px": int(region.sum()),
                                "psnr": round(-10 * np.log10(max(mse, 1e-10)), 3)})
    return {name: {"views": len(v), "worst_psnr": float(min(x["psnr"] for x in v)) if v else None,
                   "worst_view": min(v, key=lambda x: x["psnr"])["view"] if v else None,
                   "mean_psnr": round(float(np.mean([x["psnr"] for x in v])), 3) if v else None, "per_view": v}
            for name, v in views.items()}


def _uncovered_summary(per_seed: list[dict]) -> dict:
    """Per result: the worst view of every seed and over all seeds, and the mean over all views."""
    out = {}
    for name in per_seed[0]["uncovered"]:
        rows = [r["uncovered"][name] for r in per_seed]
        views = [v["psnr"] for row in rows for v in row["per_view"]]
        out[name] = {"worst_per_seed": [row["worst_psnr"] for row in rows],
                     "mean_per_seed": [row["mean_psnr"] for row in rows],
                     "worst": min(views) if views else None,
                     "mean": round(float(np.mean(views)), 3) if views else None, "views": len(views)}
    return out


def _summary(per_seed: list[dict]) -> list[dict]:
    summary = []
    for name in per_seed[0]["summary"]:
        views = [v for r in per_seed for v in r["views"][name]]
        summary.append({"row": name, "views": len(views), **_mean(views)})
    return summary


def _mean(views: list[dict]) -> dict:
    return {m: round(float(np.mean([v[m] for v in views if m in v])), 3) for m in METRICS
            if any(m in v for v in views)}


def read_scene_cameras(scene_dir: Path):
    from phirie_jax.io.scene import load_scene

    return load_scene(scene_dir, check_images=False).cameras


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[7001, 7002, 7003])
    parser.add_argument("--scene-root", type=Path, default=Path("/tmp/bg_eval/scenes"))
    parser.add_argument("--work", type=Path, default=Path("/tmp/bg_eval/work"))
    parser.add_argument("--out", type=Path, default=Path("experiments/results/background_eval.json"))
    parser.add_argument("--fitted", action="store_true", help="also every scene with fitted Gaussians")
    parser.add_argument("--fit-steps", type=int, default=None, help="with --fitted: Adam steps of the fit")
    parser.add_argument("--candidates", action="store_true",
                        help="external candidates beside each scene (objects_eval's gen_a / gen_b)")
    args = parser.parse_args()
    if set(args.seeds) & set(DEV_SEEDS):
        print(f"note: seeds {sorted(set(args.seeds) & set(DEV_SEEDS))} were used while developing")
    import jax

    per_seed = [evaluate_seed(s, args.scene_root, args.work, candidates=args.candidates) for s in args.seeds]
    summary = _summary(per_seed)
    out = {
        "what": "background branch vs the true background (hidden tabletop included), held-out views",
        "preset": "default", "seeds": args.seeds, "external_candidates": args.candidates, "dev_seeds_excluded": list(DEV_SEEDS),
        "held_out_views_per_seed": HELD_OUT, "region_weight": REGION_WEIGHT,
        "machine": {"platform": platform.platform(), "jax_backend": jax.default_backend(), "cpus": os.cpu_count(),
                    "load_average_at_end": os.getloadavg()},
        "summary": summary,
        "uncovered": _uncovered_summary(per_seed), "visible_change": VISIBLE_CHANGE,
        "ghosts": [r["ghosts"] for r in per_seed], "collateral": [r["collateral"] for r in per_seed],
        "ghosts_per_object": [r["ghosts_per_object"] for r in per_seed],
        "object_gaussians": [r["object_gaussians"] for r in per_seed],
        "background_wall_s": {name: [r[f"run_{name}"]["wall_s"] for r in per_seed] for name in VARIANTS},
        "per_seed": per_seed,
    }
    if args.fitted:
        from phirie_jax.synthetic.fitted import fit_config_for

        fit_config = fit_config_for("default", args.fit_steps)
        fitted = [evaluate_seed(s, args.scene_root, args.work, fit_config, args.candidates) for s in args.seeds]
        out["fitted"] = {"summary": _summary(fitted), "uncovered": _uncovered_summary(fitted), "per_seed": fitted,
                         "fits": [json.loads((_scene(args.scene_root, s, fit_config, args.candidates) / "gt" / "fit.json").read_text())
                                  for s in args.seeds]}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1, default=float) + "\n")
    for row in summary + [{**r, "row": f"{r['row']} (fitted)"} for r in out.get("fitted", {}).get("summary", [])]:
        print(f"{row['row']:42s} PSNR in {row['psnr_in']:6.2f}  SSIM in {row['ssim_in']:.3f}  "
              f"PSNR out {row['psnr_out']:6.2f}  hidden PSNR {row.get('psnr_hidden', float('nan')):6.2f} "
              f"SSIM {row.get('ssim_hidden', float('nan')):.3f}  ({row['views']} views)")
    for part, uncovered in (("", out["uncovered"]), (" (fitted)", out.get("fitted", {}).get("uncovered", {}))):
        for name, u in uncovered.items():
            print(f"uncovered region{part}, {name:40s} worst view {u['worst']} dB (per seed "
                  f"{[float(w) for w in u['worst_per_seed']]}), "
                  f"mean {u['mean']} dB over {u['views']} capture views")


if __name__ == "__main__":
    main()
