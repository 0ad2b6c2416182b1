"""Triangle meshes from files (glb, gltf, obj, ply, stl, ...): one reader for every stage."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from phirie_jax.errors import SceneInputError

# the first line of an object's mesh.obj (``construct.objects.assets.write_obj``): "v x y z" lines
# then "f a b c" lines (1-based) follow, as many as it counts
ASSET_OBJ_HEADER = "# phirie asset mesh: {vertices} vertices, {triangles} triangles, metres, +z up\n"
_ASSET_COUNTS = re.compile(rb"# phirie asset mesh: (\d+) vertices, (\d+) triangles, ")


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
    """(vertices (V, 3) float64, faces (F, 3) int64) of a mesh file, as stored. An object's own
    mesh.obj is parsed by NumPy (``read_asset_obj``, 2.4× faster: ``experiments/bench_asset_meshes``);
    any other file by trimesh."""
    path = Path(path)
    arrays = read_asset_obj(path) if path.suffix.lower() == ".obj" and path.is_file() else None
    if arrays is not None:
        return arrays
    mesh = load_trimesh(path)
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64).reshape(-1, 3)


def read_asset_obj(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(vertices, faces) of an OBJ in the layout ``ASSET_OBJ_HEADER`` announces, or None when the
    file is not exactly that (trimesh reads it then). The same numbers as trimesh's reading: each
    decimal parsed to the nearest float64."""
    data = path.read_bytes()
    header, _, body = data.partition(b"\n")
    counts = _ASSET_COUNTS.match(header)
    if counts is None:
        return None
    nv, nf = int(counts[1]), int(counts[2])
    if body.count(b"v ") != nv or body.count(b"f ") != nf or body.count(b"\n") != nv + nf:
        return None
    if not nf:
        split = len(body)
    elif nv:
        split = body.find(b"\nf ") + 1   # the first triangle's line (0: none)
        if split == 0:
            return None
    else:
        split = 0

    def numbers(text: bytes, tag: bytes, dtype) -> np.ndarray | None:
        """The numbers of the text, or None when something else is in it (NumPy raises, or warns
        and stops short: refused by the counts below)."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            try:
                return np.fromstring(text.replace(tag, b" ").decode("ascii", "replace"), dtype=dtype, sep=" ")
            except ValueError:
                return None

    vertices, faces = numbers(body[:split], b"v ", np.float64), numbers(body[split:], b"f ", np.int64)
    if vertices is None or faces is None:
        return None
    if vertices.size != 3 * nv or faces.size != 3 * nf or (nf and (faces.min() < 1 or faces.max() > nv)):
        return None
    return vertices.reshape(-1, 3), faces.reshape(-1, 3) - 1
