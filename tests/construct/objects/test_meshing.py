"""Occupancy grids → meshes: closed, outward, with the grid's volume."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from phirie_jax.construct.objects.meshing import largest_component, occupancy_mesh


@pytest.mark.parametrize("smooth", [0.0, 0.8])
def test_random_blobs_give_closed_outward_meshes_with_the_grid_volume(smooth):
    rng = np.random.default_rng(0)
    from scipy import ndimage

    occ = ndimage.gaussian_filter(rng.random((24, 20, 18)), 2.0) > 0.5
    occ = largest_component(occ)
    voxel = 0.01
    v, f = occupancy_mesh(occ, np.array([1.0, 2.0, 3.0]), voxel, smooth)
    mesh = trimesh.Trimesh(v, f, process=True)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0  # outward normals
    assert mesh.volume == pytest.approx(occ.sum() * voxel**3, rel=0.25)
    # vertices stay within half a voxel of the occupied cells' box (the origin is honoured)
    idx = np.argwhere(occ)
    lo = np.array([1.0, 2.0, 3.0]) + (idx.min(0) - 0.5) * voxel
    hi = np.array([1.0, 2.0, 3.0]) + (idx.max(0) + 0.5) * voxel
    assert np.all(v >= lo - 1e-9) and np.all(v <= hi + 1e-9)


def test_each_grid_edge_gives_one_vertex_shared_by_its_faces():
    """Vertices are deduplicated by grid edge: no two coincide, and every one is used."""
    occ = np.zeros((9, 8, 7), bool)
    occ[2:7, 2:6, 1:5] = True
    occ[4, 3:5, 5] = True
    v, f = occupancy_mesh(occ, np.zeros(3), 0.5)
    assert len(np.unique(v.round(9), axis=0)) == len(v)
    assert np.array_equal(np.unique(f), np.arange(len(v)))
    mesh = trimesh.Trimesh(v, f, process=False)  # closed as it is: faces share vertices by index
    assert mesh.is_watertight and mesh.volume > 0


def test_single_voxel_and_empty_grids():
    occ = np.zeros((3, 3, 3), bool)
    v, f = occupancy_mesh(occ, np.zeros(3), 1.0)
    assert len(f) == 0
    occ[1, 1, 1] = True
    v, f = occupancy_mesh(occ, np.zeros(3), 1.0)
    mesh = trimesh.Trimesh(v, f, process=True)
    assert mesh.is_watertight and mesh.volume > 0


def test_largest_component_keeps_the_biggest_blob():
    occ = np.zeros((10, 10, 10), bool)
    occ[0:2, 0:2, 0:2] = True
    occ[5:9, 5:9, 5:9] = True
    out = largest_component(occ)
    assert out.sum() == 64 and out[6, 6, 6] and not out[0, 0, 0]
