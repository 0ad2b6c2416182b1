"""Mesh files: an object's own mesh.obj parsed by NumPy equals trimesh's reading; anything else goes to trimesh."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from phirie_jax.construct.objects.assets import write_obj
from phirie_jax.errors import SceneInputError
from phirie_jax.io.mesh import load_trimesh, read_asset_obj, read_mesh


def trimesh_arrays(path):
    mesh = load_trimesh(path)
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)


@pytest.fixture
def asset(tmp_path):
    rng = np.random.default_rng(0)
    sphere = trimesh.creation.icosphere(subdivisions=3)
    vertices = sphere.vertices * 0.07 + rng.normal(0, 0.01, 3)   # negative coordinates, 7 decimals
    path = tmp_path / "mesh.obj"
    write_obj(path, vertices, sphere.faces)
    return path, vertices, np.asarray(sphere.faces)


def test_an_asset_mesh_reads_as_trimesh_reads_it(asset):
    path, vertices, faces = asset
    fast = read_asset_obj(path)
    assert fast is not None
    slow = trimesh_arrays(path)
    for a, b in zip(fast, slow):
        np.testing.assert_array_equal(a, b)
    assert fast[0].dtype == np.float64 and fast[1].dtype == np.int64
    np.testing.assert_array_equal(fast[1], faces)
    np.testing.assert_allclose(fast[0], vertices, atol=5e-8)          # the file's 7 decimals
    for a, b in zip(read_mesh(path), fast):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("damage", ["counts", "number", "index", "extra line", "no header"])
def test_any_other_obj_goes_to_trimesh(asset, damage):
    path, _, _ = asset
    text = path.read_text()
    header, _, body = text.partition("\n")
    if damage == "counts":
        text = header.replace(" vertices", "0 vertices", 1) + "\n" + body
    elif damage == "number":
        text = text.replace("v ", "v x", 1)
    elif damage == "index":
        text = text.replace("\nf 1 ", "\nf 0 ", 1) if "\nf 1 " in text else text.replace("\nf ", "\nf 0 1 2\nf ", 1)
    elif damage == "extra line":
        text = text + "vn 0 0 1\n"
    else:
        text = body
    path.write_text(text)
    assert read_asset_obj(path) is None
    try:
        expected = trimesh_arrays(path)
    except SceneInputError:
        with pytest.raises(SceneInputError):
            read_mesh(path)
        return
    for a, b in zip(read_mesh(path), expected):
        np.testing.assert_array_equal(a, b)
