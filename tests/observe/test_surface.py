"""The splat-derived surface: TSDF of a rendered sphere, surface nets on an exact SDF,
both backends agree, real RGB-D frames fuse to a plausible surface, and a scene with
no surface and no way to build one is a clear error."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import trimesh

from phirie_jax.errors import SceneInputError
from phirie_jax.observe.config import ObserveConfig, SurfaceConfig
from phirie_jax.observe.raycast import pixel_grid, pixel_rays
from phirie_jax.observe.stage import scene_surface
from phirie_jax.observe.surface import active_blocks, fuse_depths, surface_nets
from phirie_jax.types import SceneInput
from tests.conftest import shared_data
from tests.observe.helpers import ring

SPHERE_VOXEL = 0.01
NETS_TOL = 0.1          # surface nets on an exact linear-ish SDF: vertex error in voxels
BACKENDS_TOL = 1.0      # the two backends' surfaces agree within one voxel (median distance)
MANIFOLD_EDGES = 0.93   # real RGB-D: fraction of edges shared by exactly two faces
BOUNDARY_EDGES = 0.06   # real RGB-D: fraction of edges on a patch boundary


def sphere_depths(cameras, centre, radius):
    out = []
    for cam in cameras:
        o, d = pixel_rays(cam, *pixel_grid(cam.width, cam.height))
        oc = o - centre
        a, b, c = (d * d).sum(1), 2 * (oc * d).sum(1), (oc * oc).sum(1) - radius**2
        disc = b * b - 4 * a * c
        t = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), 0.0)
        out.append(t.reshape(cam.height, cam.width))
    return out


def sphere_views():
    cams = ring(8, 0.6, 0.35, width=64, height_px=48, focal=80.0) + \
        ring(8, 0.6, -0.3, width=64, height_px=48, focal=80.0, offset=0.4)
    centre, radius = np.array([0.013, -0.021, 0.007]), 0.1
    return cams, centre, radius, sphere_depths(cams, centre, radius)


@pytest.mark.parametrize("backend", ["jax", "open3d"])
def test_tsdf_of_a_rendered_sphere_recovers_its_radius_within_one_voxel(backend):
    cams, centre, radius, depths = sphere_views()
    mesh = fuse_depths(depths, cams, SurfaceConfig(voxel=SPHERE_VOXEL, truncation=0.03, backend=backend))
    r = np.linalg.norm(mesh.vertices - centre, axis=1)
    assert len(mesh.faces) > 1000
    assert abs(r.mean() - radius) < SPHERE_VOXEL
    assert np.all(np.abs(r - radius) < SPHERE_VOXEL)
    tm = mesh.to_trimesh()
    assert tm.is_winding_consistent and tm.volume > 0  # outward-facing
    assert abs(tm.volume - 4 / 3 * np.pi * radius**3) < 0.1 * 4 / 3 * np.pi * radius**3


def test_backends_agree():
    cams, _centre, _radius, depths = sphere_views()
    meshes = [fuse_depths(depths, cams, SurfaceConfig(voxel=SPHERE_VOXEL, truncation=0.03, backend=b))
              for b in ("jax", "open3d")]
    ref = meshes[1].to_trimesh()
    _, dist, _ = trimesh.proximity.closest_point(ref, meshes[0].vertices)
    assert np.median(dist) < BACKENDS_TOL * SPHERE_VOXEL


def test_surface_nets_on_an_exact_sdf_is_closed_and_on_the_surface():
    voxel, res, radius = 0.01, 8, 0.073
    blocks = np.stack(np.meshgrid(*[np.arange(-2, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)
    local = np.stack(np.meshgrid(*[np.arange(res)] * 3, indexing="ij"), -1)
    centres = (blocks[:, None, None, None, :] * res + local[None] + 0.5) * voxel
    sdf = np.linalg.norm(centres, axis=-1) - radius  # outside positive, like a TSDF
    vertices, faces = surface_nets(blocks, np.clip(sdf / 0.03, -1, 1), np.ones(sdf.shape), voxel)
    mesh = trimesh.Trimesh(vertices, faces, process=True)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert np.all(np.abs(np.linalg.norm(vertices, axis=1) - radius) < NETS_TOL * voxel)
    # an unobserved voxel (weight 0) opens a hole instead of inventing surface
    weight = np.ones(sdf.shape)
    weight.reshape(-1, 1)[np.argmin(np.abs(sdf.reshape(-1)))] = 0
    _, holed = surface_nets(blocks, np.clip(sdf / 0.03, -1, 1), weight, voxel)
    assert 0 < len(holed) < len(faces)


def test_active_blocks_cover_the_truncation_band():
    cams, centre, radius, depths = sphere_views()
    voxel, res, trunc = 0.01, 8, 0.03
    blocks = {tuple(b) for b in active_blocks(depths, cams, trunc, voxel, res, stride=1)}
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(2000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    for shell in (radius - trunc + 0.002, radius, radius + trunc - 0.002):  # inside the band
        pts = centre + shell * dirs
        # only points that a camera sees near the surface: the sphere is seen from all around
        cells = {tuple(b) for b in np.floor(pts / (voxel * res)).astype(int)}
        assert len(cells - blocks) <= 0.02 * len(cells)


def test_real_rgbd_frames_fuse_to_a_plausible_surface():
    from tests.fixtures.rgbd import read_rgbd_cameras

    root = shared_data("rgbd")
    cams = read_rgbd_cameras(root / "camera_primesense.json", root / "trajectory.log", root / "color")
    depths = [cv2.imread(str(root / "depth" / f"{i:05d}.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / 1000.0
              for i in range(len(cams))]
    config = SurfaceConfig(voxel=0.01, truncation=0.04, backend="jax", depth_max=3.0)
    mesh = fuse_depths(depths, cams, config).to_trimesh()
    assert len(mesh.faces) > 20_000
    # closed patches: nearly every edge joins exactly two faces (measured: 95.3% two, 4.2%
    # boundary — the edge of what the camera saw —, 0.5% shared by 3–4 faces where one
    # surface-nets cell holds two sheets)
    edges = np.sort(mesh.edges, axis=1)
    _, uses = np.unique(edges, axis=0, return_counts=True)
    assert np.mean(uses == 2) > MANIFOLD_EDGES and np.mean(uses == 1) < BOUNDARY_EDGES
    # most of the area is in a few large connected patches (measured: 95% in the largest 5)
    patch = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    areas = np.sort(np.bincount(patch, weights=mesh.area_faces))[::-1]
    assert areas[:5].sum() > 0.8 * mesh.area
    # extent: in the first camera the surface spans the depth range of the measurements
    cam = cams[0]
    z = (mesh.vertices @ cam.world_to_camera[:3, :3].T + cam.world_to_camera[:3, 3])[:, 2]
    valid = depths[0][(depths[0] > 0) & (depths[0] <= 3.0)]
    lo, hi = np.percentile(valid, [1, 99])
    assert np.percentile(z, 1) > lo - 0.15 and np.percentile(z, 99) < hi + 0.15
    # and the surface passes through the back-projected depth of every frame (median < one voxel)
    from phirie_jax.observe.surface import backproject

    for depth, cam in zip(depths, cams):
        pts, _ = backproject(np.where(depth <= 3.0, depth, 0), cam, stride=16)
        _, dist, _ = trimesh.proximity.closest_point(mesh, pts)
        assert np.median(dist) < config.voxel


def test_no_surface_and_no_way_to_build_one(tmp_path):
    bare = SceneInput(root=tmp_path, layout="colmap", gaussians=None, gaussians_path=None,
                      cameras=tuple(ring(2, 1.0, 0.5)))
    with pytest.raises(SceneInputError, match="surface: no scan mesh and no way to build one"):
        scene_surface(bare, ObserveConfig(), tmp_path)
    with pytest.raises(SceneInputError, match="no scan mesh"):
        scene_surface(bare, ObserveConfig(surface_source="mesh"), tmp_path)


def test_snapping_moves_a_biased_plane_onto_the_centres_and_leaves_the_rest():
    from phirie_jax.observe.surface import snap_to_centres

    n = 31
    grid = np.stack(np.meshgrid(np.linspace(0, 0.3, n), np.linspace(0, 0.3, n), indexing="ij"), -1).reshape(-1, 2)
    quads = [(i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1) for i in range(n - 1) for j in range(n - 1)]
    faces = np.array([f for a, b, c, d in quads for f in ((a, b, c), (a, c, d))])
    vertices = np.c_[grid, np.full(len(grid), 0.004)]  # 4 mm in front of the true surface z = 0
    rng = np.random.default_rng(0)
    centres = np.c_[rng.uniform(0, 0.2, 4000), rng.uniform(0, 0.3, 4000), np.zeros(4000)]  # evidence where x < 0.2
    moved, offset = snap_to_centres(vertices, faces, centres, radius=0.015, neighbours=8)
    covered = vertices[:, 0] < 0.18
    np.testing.assert_allclose(moved[covered, 2], 0.0, atol=1e-9)
    np.testing.assert_allclose(moved[covered, :2], vertices[covered, :2], atol=1e-9)
    far = vertices[:, 0] > 0.22
    np.testing.assert_array_equal(moved[far], vertices[far])
    assert np.all(offset[far] == 0)


def test_a_grid_over_the_memory_budget_is_refused_before_fusing(monkeypatch):
    import phirie_jax.observe.surface as surface_mod
    from phirie_jax.errors import SurfaceTooLargeError

    def never(*args, **kwargs):
        raise AssertionError("the grid was allocated")

    monkeypatch.setattr(surface_mod, "fuse_open3d", never)
    monkeypatch.setattr(surface_mod, "fuse_jax", never)
    cams, _centre, _radius, depths = sphere_views()
    for backend in ("open3d", "jax"):
        config = SurfaceConfig(voxel=SPHERE_VOXEL, truncation=0.03, backend=backend, memory_budget_gb=1e-4)
        with pytest.raises(SurfaceTooLargeError) as err:
            fuse_depths(depths, cams, config)
        message = str(err.value)
        assert "\n" not in message and message.startswith("observe.surface: the depth samples span [")
        assert f"at voxel {SPHERE_VOXEL:g} the {backend} TSDF needs" in message
        assert "blocks of 8³" in message and "> memory_budget_gb 0.0001" in message
    plan = surface_mod.plan_grid(depths, cams, SurfaceConfig(voxel=SPHERE_VOXEL, truncation=0.03))
    # the samples lie on the sphere: their bounds are the sphere's visible part
    assert np.all(plan.bounds[0] > _centre - _radius - 1e-6) and np.all(plan.bounds[1] < _centre + _radius + 1e-6)


def sphere_gaussians(centre, radius, n=4000):
    """Opaque grey Gaussians (4 mm, isotropic) on a sphere (a Fibonacci lattice)."""
    from phirie_jax.types import GaussianSplatData

    i = np.arange(n) + 0.5
    z, phi = 1 - 2 * i / n, np.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z * z)
    means = centre + radius * np.c_[r * np.cos(phi), r * np.sin(phi), z]
    return GaussianSplatData(means=means.astype(np.float32), quats=np.tile([1.0, 0, 0, 0], (n, 1)).astype(np.float32),
                             log_scales=np.full((n, 3), np.log(0.004), np.float32),
                             opacity_logits=np.full(n, 4.0, np.float32), sh=np.zeros((n, 1, 3), np.float32))


def test_working_width_renders_smaller_and_gives_the_same_surface(tmp_path):
    cams, centre, radius, _ = sphere_views()
    cams = [c.scaled(2.0) for c in cams]  # 128×96 photos
    scene = SceneInput(root=tmp_path, layout="gaussians", gaussians=sphere_gaussians(centre, radius),
                       gaussians_path=None, cameras=tuple(cams))
    surface = SurfaceConfig(voxel=SPHERE_VOXEL, truncation=0.03, snap_radius=0.0)
    full, full_record = scene_surface(scene, ObserveConfig(working_width=0, surface=surface), tmp_path / "a")
    half, half_record = scene_surface(scene, ObserveConfig(working_width=64, surface=surface), tmp_path / "b")
    assert full_record["render_size"] == [128, 96] and half_record["render_size"] == [64, 48]
    assert full_record["floaters"]["kept"] == 4000
    _, dist, _ = trimesh.proximity.closest_point(full.to_trimesh(), half.vertices)
    assert np.median(dist) < SPHERE_VOXEL
    r = np.linalg.norm(half.vertices - centre, axis=1)
    assert abs(np.median(r) - radius) < SPHERE_VOXEL
