"""End to end on a rendered synthetic scene (``synthesize``, splat renderer): mask files
with the scan mesh and with the splat-derived surface. Slow: it renders every view."""

from __future__ import annotations

import pytest

from phirie_jax.observe.config import ObserveConfig, SurfaceConfig

pytestmark = pytest.mark.slow

CONFIG = ObserveConfig(pixel_stride=1)
SURFACE_TOL = 0.005  # median distance of the fused table top to the true one (one TSDF voxel)


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    """Between the ``tiny`` and ``default`` presets: 12 views of 160×120, splats a few mm wide
    (``tiny``'s 64×48 views leave objects a few pixels wide and its table splats 16 mm wide)."""
    from phirie_jax.synthetic import scene as synthetic

    preset = synthetic.SynthConfig(num_objects=(3, 3), num_cameras=12, rings=((1.2, 1.35), (0.95, 1.6)),
                                   width=160, height=120, object_spacing=0.004, table_spacing=0.008,
                                   floor_spacing=0.04, floor_size=2.0, floaters=8, boundary_blobs=6)
    root = tmp_path_factory.mktemp("scene")
    with pytest.MonkeyPatch.context() as patch:
        patch.setitem(synthetic.PRESETS, "observe-test", preset)
        scene = synthetic.synthesize(root, "observe-test", 3)
    return root, scene


@pytest.mark.parametrize("backend", ["jax", "open3d"])
def test_splat_derived_surface_with_mask_files(tiny_scene, tmp_path, backend):
    import numpy as np
    import trimesh

    root, scene = tiny_scene
    config = ObserveConfig(pixel_stride=1, surface_source="splats", surface=SurfaceConfig(backend=backend))
    manifest = run(root, tmp_path, config)
    surface = manifest["observe"]["surface"]
    assert surface["kind"] == "splats" and surface["backend"] == backend and surface["faces"] > 1000
    mesh = trimesh.load(tmp_path / "observe" / "surface.ply", process=False)
    # the fused surface lies on the true one where the table is (median within a voxel)
    top = mesh.vertices[np.abs(mesh.vertices[:, 2] - scene.furniture.table_top_z) < 0.02]
    assert len(top) > 100
    _, dist, _ = trimesh.proximity.closest_point(trimesh.util.concatenate(
        [scene.furniture.table, *[o.world_mesh() for o in scene.objects]]), top)
    assert np.median(dist) < SURFACE_TOL
    assert [i["id"] for i in manifest["instances"]] == [o.id for o in scene.objects]


def test_scan_mesh_with_mask_files_finds_every_object(tiny_scene, tmp_path):
    root, scene = tiny_scene
    manifest = run(root, tmp_path, CONFIG)
    assert [i["id"] for i in manifest["instances"]] == [o.id for o in scene.objects]


def run(root, out, config):
    from phirie_jax.observe.stage import run_observe

    return run_observe(root, out, config, masks="files")
