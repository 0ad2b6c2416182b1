"""Asset Gaussians: the host transform equals the JAX one; captured selection; fill of unseen regions;
stale object folders of an earlier run."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from kernels.gaussians import Sim3, transform_gaussians
from phirie_jax.construct.objects import assets
from phirie_jax.observe.raycast import Raycaster
from phirie_jax.types import GaussianSplatData

TOL = 2e-5


def random_splats(n, rng, degree=3):
    return GaussianSplatData(
        means=rng.normal(0, 0.1, (n, 3)).astype(np.float32), quats=rng.normal(size=(n, 4)).astype(np.float32),
        log_scales=rng.normal(-5, 0.5, (n, 3)).astype(np.float32),
        opacity_logits=rng.normal(0, 1, n).astype(np.float32),
        sh=rng.normal(0, 0.3, (n, (degree + 1) ** 2, 3)).astype(np.float32))


def test_host_transform_equals_the_kernel_transform():
    rng = np.random.default_rng(0)
    data = random_splats(40, rng)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = 0.37 * q, [0.1, -2.0, 0.5]
    host = assets.transform_splats(data, m)
    ref = transform_gaussians(data.to_kernel(), Sim3.from_matrix(jnp.asarray(m, jnp.float32)))
    np.testing.assert_allclose(host.means, np.asarray(ref.means), atol=TOL)
    np.testing.assert_allclose(host.log_scales, np.asarray(ref.log_scales), atol=TOL)
    np.testing.assert_allclose(host.sh, np.asarray(ref.sh), atol=1e-4)
    unit = lambda x: x / np.linalg.norm(x, axis=1, keepdims=True) * np.sign(x[:, :1])  # noqa: E731
    np.testing.assert_allclose(unit(host.quats), unit(np.asarray(ref.quats)), atol=1e-4)


def test_captured_selection_and_fill_of_the_unseen_bottom():
    rng = np.random.default_rng(1)
    cube = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    cube.apply_translation([0, 0, 0.05])
    surface, face = trimesh.sample.sample_surface(cube, 3000, seed=0)
    top_and_sides = surface[cube.face_normals[face][:, 2] > -0.5]
    table = np.column_stack([rng.uniform(-0.2, 0.2, (500, 2)), np.zeros(500)])
    far = rng.uniform(1, 2, (50, 3))
    means = np.concatenate([top_and_sides, table, far]).astype(np.float32)
    n = len(means)
    sh = np.zeros((n, 1, 3), np.float32)
    sh[: len(top_and_sides), 0] = [1.0, -1.0, 0.5]  # the object's colour
    scene = GaussianSplatData(means, np.tile([1, 0, 0, 0], (n, 1)).astype(np.float32),
                              np.full((n, 3), -6, np.float32), np.zeros(n, np.float32), sh)
    q = top_and_sides[::3]
    idx = assets.captured_gaussians(scene, q, Raycaster(cube.vertices, cube.faces), means[:, 2].astype(np.float64),
                                    0.01, 0.003)
    assert set(idx.tolist()) <= set(range(len(top_and_sides)))        # no table, no floaters
    assert len(idx) > 0.95 * np.sum(top_and_sides[:, 2] > 0.003)
    kept = scene.subset(idx)
    fill, info = assets.fill_gaussians(cube.vertices, cube.faces, kept, 0.005, 0.008, 4, 0)
    assert fill.num > 0 and 0.1 < info["unseen_fraction"] < 0.3          # the bottom face: 1/6 of the area
    assert np.all(fill.means[:, 2] < 0.01)
    np.testing.assert_allclose(fill.sh[:, 0], np.tile([1.0, -1.0, 0.5], (fill.num, 1)), atol=1e-6)
    both = GaussianSplatData.join([kept, fill])
    assert both.num == kept.num + fill.num
    # where a camera saw through the mesh, no disk: the bottom face "seen through" leaves nothing
    none, info = assets.fill_gaussians(cube.vertices, cube.faces, kept, 0.005, 0.008, 4, 0,
                                       seen=lambda p: p[:, 2] < 0.01)
    assert none.num == 0 and info["seen_fraction"] == pytest.approx(info["unseen_fraction"])


def test_stale_object_folders_go_and_folders_with_foreign_files_stay(tmp_path):
    def put(rel, text="x"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)

    put("objects/1/mesh.obj")                                   # this run's object: kept
    for rel in ("mesh.obj", "visual.ply", "object.urdf", "collision/part_00.obj", "collision/part_13.obj",
                ".visual.ply.k2j4.tmp"):                         # a previous run's object: removed
        put(f"objects/2/{rel}")
    put("objects/3/mesh.obj")
    put("objects/3/notes.txt")                                   # someone else's file: kept
    put("objects/extra/mesh.obj")                                # not an object folder: untouched
    result = assets.remove_stale_object_folders(tmp_path, {1})
    assert result == {"removed": ["objects/2"], "kept": ["objects/3"]}
    assert (tmp_path / "objects/1/mesh.obj").exists() and not (tmp_path / "objects/2").exists()
    assert (tmp_path / "objects/3/notes.txt").exists() and (tmp_path / "objects/extra/mesh.obj").exists()
    assert assets.remove_stale_object_folders(tmp_path / "nothing_here", set()) == {"removed": [], "kept": []}


def test_the_halo_beyond_the_shape_is_not_the_objects():
    """captured_gaussians: a Gaussian 2 cm from Q_i belongs to the object when it lies inside or
    near the placed shape (fur around a plush) and not when it lies 2 cm beyond the shape (the wall
    behind a mounted head), however near Q_i."""
    import trimesh

    from phirie_jax.observe.raycast import Raycaster

    cube = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    cube.apply_translation([0, 0, 0.05])
    q = np.array([[0.049, 0.0, 0.05], [0.0, 0.0, 0.099]])        # observed on the +x and top faces
    means = np.array([[0.03, 0.0, 0.05],     # 1.9 cm inside the +x face, 1.9 cm from Q: the object's
                      [0.055, 0.0, 0.05],    # 6 mm out of the +x face: the object's (its fuzz)
                      [0.069, 0.0, 0.05],    # 2 cm from Q and 1.9 cm out of the face: the wall's
                      [0.0, 0.0, 0.118]])    # 1.9 cm above the top face: the wall's
    scene = GaussianSplatData(means=means.astype(np.float32), quats=np.tile([1.0, 0, 0, 0], (4, 1)).astype(np.float32),
                              log_scales=np.full((4, 3), -5.0, np.float32), opacity_logits=np.zeros(4, np.float32),
                              sh=np.zeros((4, 1, 3), np.float32))
    placed = Raycaster(cube.vertices, cube.faces)
    idx = assets.captured_gaussians(scene, q, placed, means[:, 2], 0.03, 0.003, mesh_radius=0.01)
    np.testing.assert_array_equal(idx, [0, 1])
    np.testing.assert_array_equal(assets.captured_gaussians(scene, q, placed, means[:, 2], 0.03, 0.003), [0, 1, 2, 3])


def test_obj_text_is_the_line_by_line_formatting(tmp_path):
    """``write_obj`` formats every number at once; the bytes are those of formatting each line."""
    rng = np.random.default_rng(3)
    vertices = rng.normal(0, 0.2, (50, 3))
    vertices[0] = [-0.0, 1e-9, -5e-8]                      # signed zero and roundings to zero
    vertices = np.vstack([vertices, vertices[:5].astype(np.float32)])  # float32 input too
    faces = rng.integers(0, len(vertices), (70, 3)).astype(np.int32)
    assets.write_obj(tmp_path / "mesh.obj", vertices, faces)
    reference = [f"# phirie asset mesh: {len(vertices)} vertices, {len(faces)} triangles, metres, +z up\n"]
    reference += [f"v {x:.7f} {y:.7f} {z:.7f}\n" for x, y, z in vertices]
    reference += [f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces]
    assert (tmp_path / "mesh.obj").read_text() == "".join(reference)
    rows = [line.split() for line in (tmp_path / "mesh.obj").read_text().splitlines()[1:]]
    np.testing.assert_allclose([[float(x) for x in r[1:]] for r in rows if r[0] == "v"], vertices, atol=5e-8)
    np.testing.assert_array_equal([[int(x) - 1 for x in r[1:]] for r in rows if r[0] == "f"], faces)
