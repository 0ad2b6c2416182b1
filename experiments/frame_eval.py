"""The scene frame against truth: the real captures (hand-found truth, ``tests/fixtures/frame_truth.json``)
and synthetic tabletops copied into a tilted, non-metric frame (with and without a printed marker).

For each: up's error (degrees), the scale against the truth and the stated band, where up and
the scale came from, every cue's angle to up, the warnings, and the frame's seconds.

    python -m experiments.frame_eval [--real] [--synthetic tiny default] [--marker-seeds 1 2 3]
                                     [--fitted tiny] [--out experiments/results/frame_eval.json]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from phirie_jax.frame.config import FrameConfig
from phirie_jax.frame.estimate import angle_deg
from phirie_jax.frame.resolve import resolve_frame
from phirie_jax.geometry import sim3_matrix, split_sim3
from phirie_jax.io.scene import load_scene

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "captures"
TRUTH = ROOT / "tests" / "fixtures" / "frame_truth.json"
UNITS_PER_METRE = 3.7
WORLD_TO_CAPTURE = sim3_matrix(UNITS_PER_METRE, Rotation.from_euler("xyz", [70, -20, 35], degrees=True).as_matrix(),
                               np.array([0.4, -1.2, 2.0]))


def frame_record(frame, seconds: float) -> dict:
    cues = {c["key"]: {"angle_to_up_deg": c["angle_to_up_deg"], "used": c["used"], "sigma_deg": c["sigma_deg"]}
            for c in frame.evidence.get("cues", [])}
    support = frame.support
    return {"up_source": frame.up_source, "scale": frame.scale, "scale_source": frame.scale_source,
            "scale_uncertainty": frame.scale_uncertainty, "scale_is_prior": frame.scale_is_prior,
            "support": None if support is None else support.record(), "cues": cues,
            "warnings": list(frame.warnings), "seconds": round(seconds, 2)}


def real(name: str, truth: dict) -> dict:
    scene = load_scene(DATA / name)
    t0 = time.perf_counter()
    frame = resolve_frame(scene)
    seconds = time.perf_counter() - t0
    record = truth[name]
    up = np.asarray(record["up"])
    low, high = frame.scale / frame.scale_uncertainty, frame.scale * frame.scale_uncertainty
    return {"capture": name, **frame_record(frame, seconds),
            "up_error_deg": round(angle_deg(frame.capture_up, up), 3),
            "cue_error_deg": {c["key"]: round(angle_deg(np.asarray(c["up"]), up), 3) for c in frame.evidence["cues"]},
            "truth_scale": record["scale"], "truth_scale_range": record["scale_range"],
            "scale_over_truth": round(frame.scale / record["scale"], 4),
            "truth_in_band": bool(low <= record["scale"] <= high),
            "truth_range_in_band": bool(low <= record["scale_range"][0] and record["scale_range"][1] <= high)}


def synthetic(preset: str, seed: int, marker: float, work: Path, fitted: bool = False) -> dict:
    from phirie_jax.synthetic import synthesize
    from phirie_jax.synthetic.fitted import synthesize_fitted
    from phirie_jax.synthetic.reframe import reframe_scene

    folder = work / f"{preset}_{seed}_{marker:g}_{'fitted' if fitted else 'ideal'}"
    t0 = time.perf_counter()
    if fitted:
        synthesize_fitted(folder / "scene", preset, seed)
    else:
        synthesize(folder / "scene", preset=preset, seed=seed, marker=marker)
    reframe_scene(folder / "scene", folder / "tilted", WORLD_TO_CAPTURE)
    made = time.perf_counter() - t0
    scene = load_scene(folder / "tilted")
    t0 = time.perf_counter()
    frame = resolve_frame(scene, FrameConfig(marker_size=marker or None))
    seconds = time.perf_counter() - t0
    scale, rotation, _ = split_sim3(frame.capture_to_world @ WORLD_TO_CAPTURE)
    return {"preset": preset, "seed": seed, "fitted": fitted, "marker_m": marker, **frame_record(frame, seconds),
            "synthesize_s": round(made, 1), "up_error_deg": round(float(np.degrees(np.arccos(min(1.0, rotation[2, 2])))), 3),
            "scale_over_truth": round(scale, 4),
            "truth_in_band": bool(1 / frame.scale_uncertainty <= scale <= frame.scale_uncertainty)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--real", action="store_true", help="the real captures in ../shared/data/captures")
    parser.add_argument("--synthetic", nargs="*", default=[], help="synthetic presets (each with seed 1, "
                        "without a marker and with a 15 cm one)")
    parser.add_argument("--fitted", nargs="*", default=[], help="synthetic presets fitted like a real capture "
                        "(phirie synth --fitted: the preset's fit, seed 1, no marker)")
    parser.add_argument("--marker-seeds", nargs="+", type=int, default=[1],
                        help="the seeds each synthetic preset is made with a marker for (without one: seed 1)")
    parser.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "frame_eval.json")
    args = parser.parse_args()
    results = {"real": [], "synthetic": []}
    if args.real:
        truth = json.loads(TRUTH.read_text())
        for name in ("snowmiku", "fox"):
            results["real"].append(real(name, truth))
            print(json.dumps(results["real"][-1]), flush=True)
    with tempfile.TemporaryDirectory() as work:
        for preset in args.synthetic:
            marker = 0.15 if preset != "tiny" else 0.25
            for seed, size in [(1, 0.0)] + [(seed, marker) for seed in args.marker_seeds]:
                results["synthetic"].append(synthetic(preset, seed, size, Path(work)))
                print(json.dumps(results["synthetic"][-1]), flush=True)
        for preset in args.fitted:
            results["synthetic"].append(synthetic(preset, 1, 0.0, Path(work), fitted=True))
            print(json.dumps(results["synthetic"][-1]), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    temporary = args.out.with_suffix(".tmp")
    temporary.write_text(json.dumps(results, indent=1) + "\n")
    temporary.rename(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
