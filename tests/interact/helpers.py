"""A constructed output folder from synthetic ground truth (what the object stage writes), fast."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from phirie_jax.construct.assets import write_obj
from phirie_jax.manifest import Manifest
from phirie_jax.synthetic.scene import build_scene, surface_mesh, write_mesh

NOT_RUN = {"value": None, "threshold": 0.03, "passed": None, "status": "not_run"}


def constructed_folder(out: Path, seed: int = 0, extra: dict[int, tuple[np.ndarray, np.ndarray]] | None = None,
                       up=(0.0, 0.0, 1.0)) -> tuple[Path, list]:
    """``out`` laid out like the object stage's output for the synthetic ``tiny`` scene of ``seed``:
    canonical ``objects/<id>/mesh.obj``, manifest ``instances`` / ``objects`` (accepted, ground-truth
    pose, settling not run) / ``construct`` (gravity up, surface). ``extra`` adds objects with the
    given (vertices, faces) at the origin of the tabletop (bad meshes for failure tests)."""
    scene = build_scene("tiny", seed)
    out.mkdir(parents=True, exist_ok=True)
    write_mesh(out / "surface.ply", surface_mesh(scene))
    instances, objects = [], []
    items = [(o.id, o.shape.category, np.asarray(o.shape.mesh.vertices), np.asarray(o.shape.mesh.faces), o.pose)
             for o in scene.objects]
    for k, (verts, faces) in (extra or {}).items():
        pose = np.eye(4)
        pose[:3, 3] = [0.0, 0.0, scene.furniture.table_top_z]
        items.append((k, "bad", verts, faces, pose))
    for oid, category, verts, faces, pose in items:
        write_obj(out / "objects" / str(oid) / "mesh.obj", verts, faces)
        instances.append({"id": oid, "category": category})
        objects.append({"id": oid, "status": "accepted", "reason": None, "candidate": "ground_truth",
                        "pose": pose, "mesh": f"objects/{oid}/mesh.obj", "visual": None, "collision": [],
                        "mass": None, "friction": None, "checks": {"settling": dict(NOT_RUN)}, "candidates": [],
                        "drop_test": None, "support": {"height": float(scene.furniture.table_top_z),
                                                       "source": "surface"}})
    manifest = Manifest(out)
    manifest.set("instances", instances)
    manifest.set("objects", objects)
    manifest.set("construct", {"gravity": {"up": list(up), "source": "test"}, "surface": "surface.ply"})
    manifest.write()
    return out, scene.objects
