"""Triangle meshes from files (glb, gltf, obj, ply, stl, ...): one reader for every stage."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from phirie_jax.errors import SceneInputError


def load_trimesh(path: str | Path, process: bool = False):
    """The file's triangles as one ``trimesh.Trimesh`` (scenes are merged, nothing repaired unless
    ``process``). A missing, unreadable or triangle-less file is a ``SceneInputError`` naming it."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise SceneInputError(path, None, "mesh file missing")
    try:
        mesh = trimesh.load(path, force="mesh", process=process)
    except Exception as err:  # noqa: BLE001 — trimesh raises many types for bad files; all mean "unreadable"
        raise SceneInputError(path, None, f"not a readable mesh ({type(err).__name__}: {err})") from None
    if not hasattr(mesh, "faces"):
        raise SceneInputError(path, None, "holds no triangles (expected a triangle mesh)")
    return mesh


def read_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64, faces (F, 3) int64) of a mesh file, as stored."""
    mesh = load_trimesh(path)
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64).reshape(-1, 3)
