"""CoACD on the synthetic object categories (and an annulus): parts, hull vertices, hull-volume /
mesh-volume ratio and time, with the physics stage's settings (threshold 0.05, ≤ 16 parts, hulls
≤ 64 vertices); prints one JSON object.

    python -m experiments.coacd_parts --out experiments/results/coacd_parts.json
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
from pathlib import Path

import numpy as np
import trimesh

from experiments.report import emit
from phirie_jax.construct.physics.collision import collision_from_mesh  # noqa: E402
from phirie_jax.construct.physics.config import PhysicsConfig  # noqa: E402
from phirie_jax.synthetic import shapes  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    config = PhysicsConfig()
    rows = []
    items = [("annulus", lambda seed: trimesh.creation.annulus(0.03, 0.05, 0.02, sections=48))]
    items += [(c, lambda seed, c=c: shapes.make_object(c, np.random.default_rng(seed), seed).mesh)
              for c in shapes.CATEGORIES]
    for name, make in items:
        for seed in range(args.seeds if name != "annulus" else 1):
            mesh = make(seed)
            col = collision_from_mesh(mesh.vertices, mesh.faces, config)
            r = col.report
            rows.append({"shape": name, "seed": seed, "triangles": len(mesh.faces), "method": r["method"],
                         "parts": r["parts"], "max_hull_vertices": max(r["hull_vertices"]),
                         "hull_volume_ratio": r["hull_volume_ratio"], "coacd_s": r["time_s"],
                         "total_s": r["total_time_s"]})
            print(json.dumps(rows[-1]), file=sys.stderr)
    summary = {}
    for name in dict.fromkeys(r["shape"] for r in rows):
        sel = [r for r in rows if r["shape"] == name]
        summary[name] = {"parts": [r["parts"] for r in sel],
                         "median_s": statistics.median(r["total_s"] for r in sel),
                         "hull_volume_ratio": [round(r["hull_volume_ratio"], 3) for r in sel]}
    result = {"host": platform.processor() or platform.machine(), "config": {
        "threshold": config.coacd_threshold, "max_parts": config.max_parts,
        "max_hull_vertices": config.max_hull_vertices, "resolution": config.coacd_resolution,
        "mcts_iterations": config.coacd_mcts_iterations}, "summary": summary, "rows": rows}
    emit(result, args.out)


if __name__ == "__main__":
    main()
