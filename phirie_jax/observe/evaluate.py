"""Instance recall and precision at 3D IoU ≥ 0.5 against synthetic ground truth.

3D IoU is defined on 1 cm occupancy of the *visible* surface:

- ground truth of object k: area-uniform samples of its world mesh (2 mm apart) that
  some camera sees first (a ray from the camera centre to the sample meets the scene's
  ground-truth surface there, and the sample projects inside the image) — what any
  observation could recover; the hidden bottom and inner faces are not asked for;
- an instance: its observed points Q_i;
- IoU = |A ∩ B| / |A ∪ B| of the two sets of 1 cm voxels.

Instances and objects are matched one to one, greedily by IoU (highest first); a match
counts when IoU ≥ 0.5. Recall = matched objects / objects; precision = matched
instances / instances.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from phirie_jax.manifest import Manifest
from phirie_jax.observe.associate import voxel_keys
from phirie_jax.observe.raycast import Raycaster
from phirie_jax.types import Camera

EVAL_VOXEL = 0.01       # occupancy grid of the IoU
IOU_THRESHOLD = 0.5
GT_SPACING = 0.002      # ground-truth surface sample spacing (5 per voxel edge)
VISIBLE_TOL = 0.003     # a sample is seen when the first hit is this close to it


def visible_samples(mesh, scene: Raycaster, cameras: list[Camera], spacing: float = GT_SPACING,
                    seed: int = 0) -> np.ndarray:
    """(P, 3) area-uniform samples of ``mesh`` that at least one camera sees first."""
    import trimesh

    count = max(64, int(np.ceil(mesh.area / spacing**2)))
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    seen = np.zeros(len(points), bool)
    for cam in cameras:
        uv, depth = cam.project(points)
        inside = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        idx = np.flatnonzero(inside & ~seen)
        if len(idx) == 0:
            continue
        rays = points[idx] - cam.center
        length = np.linalg.norm(rays, axis=1)
        hits = scene.cast(np.broadcast_to(cam.center, rays.shape), rays)
        seen[idx] = np.abs(hits.depth - 1.0) * length < VISIBLE_TOL  # depth is in units of |ray|
    return points[seen]


def iou_matrix(truth: list[np.ndarray], predicted: list[np.ndarray], voxel: float = EVAL_VOXEL) -> np.ndarray:
    """(G, P) voxel IoU between point sets."""
    gt = [voxel_keys(p, voxel) for p in truth]
    pr = [voxel_keys(p, voxel) for p in predicted]
    out = np.zeros((len(gt), len(pr)))
    for i, a in enumerate(gt):
        for j, b in enumerate(pr):
            inter = len(np.intersect1d(a, b, assume_unique=True))
            out[i, j] = inter / max(len(a) + len(b) - inter, 1)
    return out


def match(iou: np.ndarray, threshold: float = IOU_THRESHOLD) -> list[tuple[int, int, float]]:
    """One-to-one greedy matching by IoU: (gt index, predicted index, IoU) with IoU ≥ threshold."""
    pairs = sorted(((iou[g, p], g, p) for g in range(iou.shape[0]) for p in range(iou.shape[1])), reverse=True)
    used_g, used_p, out = set(), set(), []
    for value, g, p in pairs:
        if value < threshold:
            break
        if g not in used_g and p not in used_p:
            used_g.add(g)
            used_p.add(p)
            out.append((g, p, float(value)))
    return out


def aabb_iou(a, b) -> float:
    """IoU of two axis-aligned boxes ([min xyz], [max xyz])."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    inter = float(np.prod(np.clip(np.minimum(a[1], b[1]) - np.maximum(a[0], b[0]), 0, None)))
    union = float(np.prod(a[1] - a[0]) + np.prod(b[1] - b[0])) - inter
    return inter / union if union > 0 else 0.0


def evaluate(scene_dir: str | Path, out_dir: str | Path, cameras: list[Camera] | None = None) -> dict:
    """Recall / precision of the instances in ``out_dir/manifest.json`` against ``scene_dir/gt``;
    per object, the best instance's IoU and the AABB IoU of its ``bounds`` with the true mesh's."""
    import trimesh

    from phirie_jax.io.scene import load_scene

    scene_dir, out_dir = Path(scene_dir), Path(out_dir)
    objects = json.loads((scene_dir / "gt" / "objects.json").read_text())
    if cameras is None:
        cameras = list(load_scene(scene_dir, check_images=False).cameras)
    surface = trimesh.load(scene_dir / "surface.ply", force="mesh", process=False)
    caster = Raycaster(surface.vertices, surface.faces)
    meshes = [trimesh.load(scene_dir / o["mesh"], force="mesh", process=False) for o in objects]
    truth = [visible_samples(mesh, caster, cameras, seed=o["id"]) for mesh, o in zip(meshes, objects)]
    instances = Manifest.load(out_dir).get("instances", ())
    predicted = [np.load(out_dir / inst.points)["points"].astype(np.float64) for inst in instances]
    iou = iou_matrix(truth, predicted)
    matches = match(iou)
    per_object = []
    for g, obj in enumerate(objects):
        best = int(np.argmax(iou[g])) if iou.shape[1] else None
        matched = next((m for m in matches if m[0] == g), None)
        per_object.append({"id": obj["id"], "category": obj["category"], "visible_samples": len(truth[g]),
                           "best_iou": round(float(iou[g, best]), 4) if best is not None else 0.0,
                           "best_instance": instances[best].id if best is not None else None,
                           "bounds_iou": (round(aabb_iou(instances[best].bounds, meshes[g].bounds), 4)
                                          if best is not None else 0.0),
                           "matched_instance": instances[matched[1]].id if matched else None})
    return {"objects": len(objects), "instances": len(instances), "matched": len(matches),
            "recall": len(matches) / max(len(objects), 1),
            "precision": len(matches) / len(instances) if instances else 0.0,
            "per_object": per_object}
