"""Watertight triangle meshes from occupancy grids (marching tetrahedra).

The grid is padded with empty voxels, optionally smoothed, and every cube of 8 voxel
centres is split into the 6 tetrahedra around its main diagonal (the same split in every
cube, so neighbouring cubes agree on shared faces). Each tetrahedron whose corners
straddle the 0.5 level contributes one triangle (1 or 3 corners inside) or two (2
inside); vertices sit on grid edges and are shared by edge, so a closed level set gives
a closed, consistently oriented (outward) mesh. No lookup tables, no ambiguous cases.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy import ndimage

from phirie_jax.geometry import edge_keys

LEVEL = 0.5
_CORNERS = np.array([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)])
# Kuhn split: corner 0 → +e_a → +e_b → corner 7 for each permutation (a, b, c) of the axes
_TETS = np.array([[0, 4 >> a, (4 >> a) | (4 >> b), 7] for a, b, _ in itertools.permutations(range(3))])


def occupancy_mesh(occupied: np.ndarray, origin: np.ndarray, voxel: float, smooth: float = 0.0):
    """Closed surface of a boolean grid (X, Y, Z) whose voxel (i, j, k) is centred at
    origin + (i, j, k) · voxel. → (vertices (V, 3), faces (F, 3) int64), outward-facing."""
    field = np.pad(occupied.astype(np.float64), 2)
    if smooth > 0:
        field = ndimage.gaussian_filter(field, smooth, mode="constant")
    field[[0, -1], :, :] = 0.0  # the outer layer stays empty: the surface closes inside the grid
    field[:, [0, -1], :] = 0.0
    field[:, :, [0, -1]] = 0.0
    inside = field > LEVEL
    shape = np.array(field.shape)
    cubes = np.stack(np.meshgrid(*[np.arange(n - 1) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    corner_in = inside[tuple((cubes[:, None, :] + _CORNERS[None]).transpose(2, 0, 1))]  # (C, 8)
    mixed = corner_in.any(1) & ~corner_in.all(1)
    cubes = cubes[mixed]
    if len(cubes) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    strides = np.array([shape[1] * shape[2], shape[2], 1])
    corner_ids = (cubes[:, None, :] + _CORNERS[None]) @ strides                          # (C, 8) flat ids
    tet_ids = corner_ids[:, _TETS].reshape(-1, 4)                                         # (6C, 4)
    flat_field, flat_inside = field.reshape(-1), inside.reshape(-1)
    tet_in = flat_inside[tet_ids]
    count = tet_in.sum(1)
    keep = (count > 0) & (count < 4)
    tet_ids, tet_in, count = tet_ids[keep], tet_in[keep], count[keep]
    order = np.argsort(~tet_in, axis=1, kind="stable")    # inside corners first
    ids = np.take_along_axis(tet_ids, order, 1)

    edges, tris = [], []

    def add(tri_edges, tet_rows):
        """tri_edges: list of three (a, b) corner slots; one triangle per selected tet."""
        base = sum(len(e) for e in edges)
        for a, b in tri_edges:
            edges.append(np.stack([ids[tet_rows, a], ids[tet_rows, b]], 1))
        n = len(tet_rows)
        tris.append(base + np.stack([np.arange(n), n + np.arange(n), 2 * n + np.arange(n)], 1))

    one, three, two = np.flatnonzero(count == 1), np.flatnonzero(count == 3), np.flatnonzero(count == 2)
    add([(0, 1), (0, 2), (0, 3)], one)          # corner 0 inside, 1–3 outside
    add([(0, 3), (1, 3), (2, 3)], three)        # corners 0–2 inside, 3 outside
    add([(0, 2), (0, 3), (1, 3)], two)          # corners 0, 1 inside; 2, 3 outside: a quad
    add([(0, 2), (1, 3), (1, 2)], two)
    all_edges = np.concatenate(edges)
    all_tris = np.concatenate(tris)
    # each grid edge as one integer (its two flat ids, lower first): a 1-D sort, in the order of the
    # rows, that lets the other objects' threads run
    codes, inverse = np.unique(edge_keys(np.sort(all_edges, axis=1), field.size), return_inverse=True)
    unique = np.stack([codes // field.size, codes % field.size], 1)
    faces = inverse.reshape(-1)[all_tris]
    fa, fb = flat_field[unique[:, 0]], flat_field[unique[:, 1]]
    t = (LEVEL - fa) / (fb - fa)
    coords = np.stack(np.unravel_index(unique, field.shape), -1).astype(np.float64)   # (E, 2, 3)
    vertices = coords[:, 0] + t[:, None] * (coords[:, 1] - coords[:, 0])
    vertices = (vertices - 2) * voxel + np.asarray(origin, np.float64)

    faces = _outward(vertices, faces, tet_ids[np.concatenate([one, three, two, two])],
                     tet_in[np.concatenate([one, three, two, two])], field.shape)
    degenerate = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
    return vertices, faces[~degenerate]


def _outward(vertices: np.ndarray, faces: np.ndarray, tets: np.ndarray, tet_in: np.ndarray,
             shape: tuple[int, ...]) -> np.ndarray:
    """``faces`` (F, 3) turned to face away from the inside corners of the tetrahedron each came
    from (``tets`` (F, 4) flat grid ids of a grid of ``shape``, ``tet_in`` (F, 4) which are inside)."""
    p = vertices[faces]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    cells = np.stack(np.unravel_index(tets, shape), -1).astype(np.float64)
    w = tet_in[..., None]
    inner = (cells * w).sum(1) / w.sum(1)
    outer = (cells * ~w).sum(1) / (~w).sum(1)
    flip = np.sum(normal * (outer - inner), axis=1) < 0
    faces[flip] = faces[flip][:, ::-1]
    return faces


def largest_component(occupied: np.ndarray) -> np.ndarray:
    """The largest 6-connected component of a boolean grid (empty stays empty)."""
    labels, n = ndimage.label(occupied)
    if n <= 1:
        return occupied.copy()
    sizes = np.bincount(labels.ravel())[1:]
    return labels == (1 + int(np.argmax(sizes)))
