"""The registered asset's files: canonical mesh and visual Gaussians G_i.

Asset canonical frame: metres, +z up (the gravity frame's axes), origin at the centre of
the placed mesh's base; ``pose`` (canonical → scene) is then rigid, so a simulator body
can use ``mesh.obj`` as it is. ``visual.ply`` is in the same canonical frame.

G_i: a candidate's own Gaussians placed by its registration (scale included, SH rotated);
otherwise the object's captured Gaussians — centres within ``gaussian_radius`` of Q_i and
near or inside the placed mesh, above the support — moved into the canonical frame, plus new
flat Gaussians on mesh regions no kept Gaussian covers and no camera saw through (where a
camera saw past a point of the mesh, the mesh is wrong there and a disk would hide the
captured object), coloured from their nearest kept ones.
"""

from __future__ import annotations

import dataclasses
import re
import shutil
from pathlib import Path

import numpy as np

from phirie_jax.io.atomic import write_bytes
from phirie_jax.io.mesh import ASSET_OBJ_HEADER
from phirie_jax.io.ply import read_gaussian_ply, write_gaussian_ply
from phirie_jax.types import GaussianSplatData

SH_C0 = 0.28209479177387814
FILL_OPACITY = 0.9
FILL_THICKNESS = 0.12   # short axis / long axis of a fill disk
FILL_SIGMA = 0.9        # long-axis σ as a fraction of the fill spacing
NEUTRAL_DC = 0.0        # SH DC of grey (rgb 0.5) for fill with no coloured neighbour


@dataclasses.dataclass(frozen=True)
class AssetFrame:
    pose: np.ndarray                    # (4, 4) canonical → world, rigid
    candidate_to_canonical: np.ndarray  # (4, 4) Sim(3) candidate file frame → canonical
    base: np.ndarray                    # (3,) canonical origin in the gravity frame


def asset_frame(placed_gravity_vertices: np.ndarray, gravity_to_world: np.ndarray,
                candidate_to_gravity: np.ndarray) -> AssetFrame:
    lo, hi = placed_gravity_vertices.min(0), placed_gravity_vertices.max(0)
    base = np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), lo[2]])
    to_base = np.eye(4)
    to_base[:3, 3] = base
    from_base = np.eye(4)
    from_base[:3, 3] = -base
    return AssetFrame(gravity_to_world @ to_base, from_base @ candidate_to_gravity, base)


def write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Wavefront OBJ (vertices and triangles only), written atomically."""
    # one formatting of all the numbers at once: the interpreter is held for a fifth of the time a
    # line at a time takes (the objects stage's threads share it)
    header = ASSET_OBJ_HEADER.format(vertices=len(vertices), triangles=len(faces))
    coordinates = np.asarray(vertices, np.float64).reshape(-1).tolist()
    corners = (np.asarray(faces, np.int64).reshape(-1) + 1).tolist()
    text = header + ("v %.7f %.7f %.7f\n" * len(vertices)) % tuple(coordinates) \
        + ("f %d %d %d\n" * len(faces)) % tuple(corners)
    write_bytes(path, text.encode("ascii"))


def transform_splats(data: GaussianSplatData, matrix: np.ndarray) -> GaussianSplatData:
    """Gaussians moved by a 4×4 similarity s R | t: μ' = sRμ + t, q' = q_R ⊗ q, log s' = log s + log s_T,
    SH rotated exactly (``kernels.sh.rotate_sh``). NumPy on the host: sizes vary per object, so a
    jitted version would compile once per object (``kernels.gaussians.transform_gaussians`` is the
    same map in JAX; the tests check they agree)."""
    from kernels.sh import rotate_sh
    from phirie_jax.rotations import matrix_to_quat, quat_multiply

    block = np.asarray(matrix, np.float64)[:3, :3]
    scale = float(np.cbrt(np.linalg.det(block)))
    rot = block / scale
    quats = quat_multiply(matrix_to_quat(rot), data.quats.astype(np.float64))
    return GaussianSplatData(
        means=(scale * data.means.astype(np.float64) @ rot.T + np.asarray(matrix)[:3, 3]).astype(np.float32),
        quats=quats.astype(np.float32), log_scales=(data.log_scales + np.log(scale)).astype(np.float32),
        opacity_logits=data.opacity_logits.astype(np.float32),
        sh=rotate_sh(data.sh.astype(np.float64), rot).astype(np.float32))


def _tangent_quats(normals: np.ndarray) -> np.ndarray:
    """(P, 4) wxyz rotations whose third column is the unit normal."""
    from phirie_jax.rotations import matrix_to_quat

    helper = np.where(np.abs(normals[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    frames = np.stack([t1, np.cross(normals, t1), normals], axis=-1)
    return matrix_to_quat(frames)


def captured_gaussians(scene_gaussians: GaussianSplatData, q_world: np.ndarray, placed_mesh,
                       height_above_support: np.ndarray, radius: float, clearance: float,
                       mesh_radius: float | None = None) -> np.ndarray:
    """Indices of the scene's Gaussians that belong to this object (see the module docstring):
    within ``radius`` of Q_i, higher than ``clearance`` above the support, and within
    ``mesh_radius`` (default ``radius``) of the placed mesh or inside it; ``placed_mesh`` is an
    ``observe.raycast.Raycaster`` of the mesh in the scene."""
    from scipy.spatial import cKDTree

    means = scene_gaussians.means.astype(np.float64)
    d_q, _ = cKDTree(q_world).query(means, distance_upper_bound=radius)
    near = np.isfinite(d_q) & (height_above_support > clearance)
    idx = np.flatnonzero(near)
    return idx[placed_mesh.within(means[idx], radius if mesh_radius is None else mesh_radius)] if len(idx) else idx


def fill_gaussians(vertices: np.ndarray, faces: np.ndarray, kept: GaussianSplatData, spacing: float,
                   min_distance: float, neighbours: int, seed: int, seen=None) -> tuple[GaussianSplatData, dict]:
    """New flat Gaussians on the canonical mesh wherever no kept Gaussian is within ``min_distance``
    and, with ``seen`` ((P, 3) canonical points → (P,) bool), no camera saw that point of the
    object (or through it)."""
    import trimesh
    from scipy.spatial import cKDTree

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    count = max(16, int(round(mesh.area / spacing**2)))
    points, face = trimesh.sample.sample_surface(mesh, count, seed=seed)
    normals = np.asarray(mesh.face_normals[face])
    if kept.num:
        tree = cKDTree(kept.means.astype(np.float64))
        d, _ = tree.query(points, distance_upper_bound=min_distance)
        unseen = ~np.isfinite(d)
    else:
        unseen = np.ones(len(points), bool)
    free = np.zeros(len(points), bool)
    if seen is not None and unseen.any():
        free[unseen] = seen(points[unseen])
    points, normals = points[unseen & ~free], normals[unseen & ~free]
    n = len(points)
    k_coeffs = kept.sh.shape[1] if kept.num else 1
    sh = np.zeros((n, k_coeffs, 3), np.float32)
    if kept.num and n:
        _, nn = tree.query(points, k=min(neighbours, kept.num))
        nn = nn.reshape(n, -1)
        sh[:, 0] = kept.sh[nn, 0].mean(axis=1)
    else:
        sh[:, 0] = NEUTRAL_DC
    sigma = FILL_SIGMA * spacing
    log_scales = np.tile(np.log([sigma, sigma, FILL_THICKNESS * sigma]), (n, 1))
    data = GaussianSplatData(
        means=points.astype(np.float32), quats=_tangent_quats(normals).astype(np.float32),
        log_scales=log_scales.astype(np.float32),
        opacity_logits=np.full(n, np.log(FILL_OPACITY / (1 - FILL_OPACITY)), np.float32), sh=sh)
    return data, {"samples": int(count), "unseen_fraction": float(unseen.mean()) if count else 0.0,
                  "seen_fraction": float(free.mean()) if count else 0.0,
                  "coloured_from_neighbours": bool(kept.num)}



def candidate_gaussians(path: Path, candidate_to_canonical: np.ndarray) -> GaussianSplatData:
    """A candidate's own Gaussians (its file frame) placed in the asset's canonical frame."""
    return transform_splats(read_gaussian_ply(path), candidate_to_canonical)


def write_visual(path: Path, data: GaussianSplatData) -> None:
    write_gaussian_ply(path, dataclasses.replace(data, extra={}, layout=(), comments=()))


# What the stages write in ``objects/<id>/`` (object stage: mesh, visual; physics stage: URDF,
# collision parts), and the temporary names of interrupted atomic writes of those.
_OBJECT_FILE = re.compile(r"(mesh\.obj|visual\.ply|object\.urdf|collision/part_\d+\.obj"
                          r"|(collision/)?\.[\w.]+\.tmp)")


def remove_stale_object_folders(out_dir: Path, current_ids: set[int]) -> dict[str, list[str]]:
    """Remove ``objects/<id>/`` folders a previous run wrote for objects this run has no assets
    for. A folder holding any file the stages do not write is left alone (someone put it there).
    Returns {"removed": [...], "kept": [...]} (paths relative to ``out_dir``)."""
    removed, kept = [], []
    root = out_dir / "objects"
    for folder in sorted(root.iterdir()) if root.is_dir() else ():
        if not (folder.is_dir() and folder.name.isdigit()) or int(folder.name) in current_ids:
            continue
        entries = [(e.relative_to(folder).as_posix(), e.is_dir()) for e in folder.rglob("*")]
        ours = all(name == "collision" if is_dir else _OBJECT_FILE.fullmatch(name) for name, is_dir in entries)
        if ours:
            shutil.rmtree(folder)
        (removed if ours else kept).append(folder.relative_to(out_dir).as_posix())
    return {"removed": removed, "kept": kept}
