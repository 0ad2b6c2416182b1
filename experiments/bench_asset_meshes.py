"""Host work on the objects' meshes, against the way each step replaced, in one run.

    python -m experiments.bench_asset_meshes OUT_DIR [OUT_DIR ...] [--repeats 3]
        [--out experiments/results/bench_asset_meshes_cpu.json]

Every ``objects/*/mesh.obj`` of the given conversion folders is

- read by ``io.mesh.read_asset_obj`` (NumPy) and by trimesh (the reference, still the reader of
  any other OBJ): seconds over all meshes, how many NumPy read (the others are not in the asset
  layout and go to trimesh), and whether those it read equal trimesh's arrays;
- counted by edge, as mesh repair's manifold check and orientation do: ``np.unique`` over the
  1-D ``geometry.edge_keys`` against ``np.unique`` over the (E, 2) rows (the reference): seconds,
  and whether the counts and the orientation's edge ids are equal;
- repaired whole (``collision.repair_mesh``, the edge count inside it): seconds, for scale.

Each figure is the median of ``--repeats`` passes over all meshes; the first pass is not counted
(file cache, imports). Prints JSON.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np

from experiments.report import emit


def _median_pass(fn, items, repeats: int) -> tuple[float, list]:
    """(median seconds of a pass of ``fn`` over ``items`` after one uncounted pass, the last pass's results)."""
    results = [fn(item) for item in items]
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        results = [fn(item) for item in items]
        times.append(time.perf_counter() - t0)
    return statistics.median(times), results


def _trimesh_arrays(path: Path) -> tuple[np.ndarray, np.ndarray]:
    from phirie_jax.io.mesh import load_trimesh

    mesh = load_trimesh(path)
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64).reshape(-1, 3)


def _sorted_edges(arrays: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, int]:
    vertices, faces = arrays
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    return edges, len(vertices)


def _by_keys(item: tuple[np.ndarray, int]) -> tuple[np.ndarray, np.ndarray]:
    from phirie_jax.geometry import edge_keys

    _, edge_id, counts = np.unique(edge_keys(*item), return_inverse=True, return_counts=True)
    return edge_id.reshape(-1), counts


def _by_rows(item: tuple[np.ndarray, int]) -> tuple[np.ndarray, np.ndarray]:
    _, edge_id, counts = np.unique(item[0], axis=0, return_inverse=True, return_counts=True)
    return edge_id.reshape(-1), counts


def bench(folders: list[Path], repeats: int) -> dict:
    from phirie_jax import layout
    from phirie_jax.construct.physics.collision import MeshError, repair_mesh
    from phirie_jax.io.mesh import read_asset_obj

    paths = sorted(p for folder in folders for p in (folder / layout.OBJECTS).glob(f"*/{layout.OBJECT_MESH}"))
    if not paths:
        raise SystemExit(f"no objects/*/{layout.OBJECT_MESH} under {', '.join(map(str, folders))}")
    read_s, ours = _median_pass(read_asset_obj, paths, repeats)
    reference_read_s, theirs = _median_pass(_trimesh_arrays, paths, repeats)
    layout_read = [a is not None for a in ours]
    same_arrays = all(all(np.array_equal(x, y) for x, y in zip(a, b)) for a, b in zip(ours, theirs) if a is not None)
    edges = [_sorted_edges(a) for a in theirs]
    keys_s, by_keys = _median_pass(_by_keys, edges, repeats)
    rows_s, by_rows = _median_pass(_by_rows, edges, repeats)
    same_counts = all(np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) for a, b in zip(by_keys, by_rows))

    def repaired(arrays):
        try:
            return repair_mesh(*arrays)
        except MeshError:
            return None

    repair_s, repairs = _median_pass(repaired, theirs, repeats)
    return {
        "benchmark": "asset_meshes", "folders": [str(f) for f in folders], "meshes": len(paths),
        "triangles": int(sum(len(a[1]) for a in theirs)), "repeats": repeats,
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "load_average_at_end": os.getloadavg()},
        "read": {"numpy_s": round(read_s, 4), "trimesh_s": round(reference_read_s, 4),
                 "speedup": round(reference_read_s / read_s, 2), "read_by_numpy": int(sum(layout_read)),
                 "same_arrays_as_trimesh": bool(same_arrays)},
        "edge_count": {"keys_s": round(keys_s, 4), "rows_s": round(rows_s, 4), "speedup": round(rows_s / keys_s, 2),
                       "same_edge_ids_and_counts": bool(same_counts)},
        "repair": {"whole_s": round(repair_s, 4), "repaired": int(sum(r is not None for r in repairs))},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", nargs="+", type=Path, help="conversion output folders (with objects/)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    if args.repeats < 1:
        parser.error(f"--repeats: at least 1 timed pass, got {args.repeats}")
    emit(bench(args.folders, args.repeats), args.out)


if __name__ == "__main__":
    main()
