"""Experiments import the package as it is installed (no ``sys.path`` edits) and run as modules
from the project root (``python -m experiments.NAME``)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted(p.stem for p in (ROOT / "experiments").glob("*.py") if p.stem != "__init__")


def test_no_experiment_edits_sys_path():
    edits = [name for name in SCRIPTS if "sys.path" in (ROOT / "experiments" / f"{name}.py").read_text()]
    assert not edits


def test_every_experiment_imports_as_a_module():
    script = "import importlib\n" + "".join(f"importlib.import_module('experiments.{n}')\n" for n in SCRIPTS)
    done = subprocess.run([sys.executable, "-c", script + "print('ok')"], cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0 and done.stdout.strip().endswith("ok"), done.stderr[-2000:]


def test_real_eval_moves_held_out_cameras_into_the_world_frame():
    """x_w = s R x_c + t: a point seen by the moved camera lands on the same pixel, s times deeper."""
    import numpy as np

    from experiments.real_eval import capture_to_world, held_out_split
    from phirie_jax.frame.resolve import world_camera
    from phirie_jax.geometry import rotation_to_z
    from phirie_jax.manifest import Manifest
    from phirie_jax.types import Camera

    rng = np.random.default_rng(0)
    w2c = np.eye(4)
    w2c[:3, :3] = rotation_to_z(rng.normal(size=3))
    w2c[:3, 3] = [0.1, -0.2, 3.0]
    camera = Camera("a.jpg", np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]]), w2c, 64, 48)
    sim3 = np.eye(4)
    sim3[:3, :3] = 0.25 * rotation_to_z(rng.normal(size=3))
    sim3[:3, 3] = [1.0, 2.0, -0.5]
    points = rng.normal(size=(20, 3))
    uv, depth = camera.project(points)
    uv_w, depth_w = world_camera(camera, sim3).project(points @ sim3[:3, :3].T + sim3[:3, 3])
    assert np.allclose(uv, uv_w) and np.allclose(0.25 * depth, depth_w)
    assert np.array_equal(capture_to_world(Manifest("unwritten")), np.eye(4))
    cams = tuple(Camera(f"{k:04d}.jpg", camera.K, w2c, 64, 48) for k in range(17))
    train, held = held_out_split(cams, 8)
    assert [c.name for c in held] == ["0000.jpg", "0008.jpg", "0016.jpg"] and len(train) == 14


def test_real_eval_scores_the_frame_against_the_hand_found_truth():
    """A frame at the truth's up and scale scores 0°, ratio 1, inside its band; one turned 10° and
    3× off scores 10° and a ratio 3, outside a ×/÷ 2.5 band; a capture without truth gets None."""
    import json

    import numpy as np
    from scipy.spatial.transform import Rotation

    from experiments.real_eval import FRAME_TRUTH, frame_against_truth
    from phirie_jax.records import FrameRecord

    truth = json.loads(FRAME_TRUTH.read_text())["fox"]
    up = np.asarray(truth["up"])
    exact = frame_against_truth("fox", FrameRecord(capture_up=up, scale=truth["scale"], scale_uncertainty=2.5))
    assert exact["up_error_deg"] == 0.0 and exact["scale_over_truth"] == 1.0 and exact["truth_in_band"]
    axis = np.cross(up, [1.0, 0.0, 0.0])
    turned = Rotation.from_rotvec(np.radians(10.0) * axis / np.linalg.norm(axis)).apply(up)
    off = frame_against_truth("fox", FrameRecord(capture_up=turned, scale=3 * truth["scale"], scale_uncertainty=2.5))
    assert off["up_error_deg"] == pytest.approx(10.0, abs=1e-3) and off["scale_over_truth"] == pytest.approx(3.0)
    assert not off["truth_in_band"]
    assert frame_against_truth("no such capture", FrameRecord(capture_up=up, scale=1.0)) is None


def test_discovery_scores_count_phantoms_and_match_one_to_one():
    """Issue 14's definition: an accepted object matching no true object at F1@20 ≥ 0.9 is a phantom;
    one true object matches one accepted object at most."""
    import numpy as np

    from experiments.discovery_eval import scores

    f1_20 = np.array([[0.95, 0.92, 0.10, 0.0],    # true 0: two bodies fit it; only one matches
                      [0.10, 0.05, 0.91, 0.0],    # true 1: matched
                      [0.00, 0.00, 0.20, 0.85]])  # true 2: its body is too poor a shape
    f1_40 = np.where(f1_20 > 0.5, 1.0, f1_20)
    s = scores(f1_20, f1_40)
    assert (s["objects"], s["accepted"], s["matched"], s["phantoms"]) == (3, 4, 2, 2)
    assert (s["tp"], s["fp"], s["fn"]) == (2, 2, 1)
    assert s["recall"] == round(2 / 3, 4) and s["precision"] == 0.5
    assert s["located"] == 3 and s["matches"] == [(0, 0), (1, 2)]
    none = scores(np.zeros((3, 0)), np.zeros((3, 0)))
    assert none["recall"] == 0.0 and none["precision"] is None and none["phantoms"] == 0


def test_fit_export_round_trips_and_installs(tmp_path):
    """A fit exported on one machine is the same set when read back here."""
    import numpy as np

    from experiments.fit_scenes import export_fit, read_fit
    from phirie_jax.synthetic.fitted import FitResult
    from phirie_jax.types import GaussianSplatData

    rng = np.random.default_rng(0)
    n = 7
    data = GaussianSplatData(means=rng.normal(size=(n, 3)).astype(np.float32),
                             quats=rng.normal(size=(n, 4)).astype(np.float32),
                             log_scales=rng.normal(size=(n, 3)).astype(np.float32),
                             opacity_logits=rng.normal(size=n).astype(np.float32),
                             sh=rng.normal(size=(n, 16, 3)).astype(np.float32))
    export_fit(tmp_path / "fit_tiny_3.npz", FitResult(data, {"seed": 3, "steps": 5, "device": "cuda:0"}))
    back = read_fit(tmp_path / "fit_tiny_3.npz")
    assert back.record == {"seed": 3, "steps": 5, "device": "cuda:0"}
    for field in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        assert np.array_equal(getattr(back.gaussians, field), getattr(data, field))


def test_convert_scale_counts_the_memory_of_descendants():
    """A parent holding little, its grandchild 200 MB: the tree's resident memory holds both."""
    import time

    from experiments.convert_scale import tree_rss_bytes

    hold = "import time; b = bytearray(200_000_000); b[::4096] = b'x' * len(b[::4096]); time.sleep(30)"
    parent = subprocess.Popen(["bash", "-c", f"{sys.executable} -c \"{hold}\"; true"])
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and tree_rss_bytes(parent.pid) < 200_000_000:
            time.sleep(0.2)
        assert tree_rss_bytes(parent.pid) >= 200_000_000
    finally:
        subprocess.run(["pkill", "-P", str(parent.pid)])
        parent.kill()
        parent.wait()


def test_gsplat_fit_sfm_points_lie_on_the_seen_surface(tmp_path):
    """fit_gsplat's SfM-like initialisation: points on the surface cameras see (within the noise),
    a share of mismatches, and the COLMAP file a trainer reads gives them back."""
    import numpy as np
    import trimesh

    from experiments.fit_gsplat import read_points3d, sfm_points
    from phirie_jax.io.colmap import write_colmap_text
    from tests.observe.helpers import tabletop_folder

    _, cams, _ = tabletop_folder(tmp_path, num_cameras=6, width=80, height=60)
    points, colours, record = sfm_points(tmp_path, 500, 0.002, 0.1, seed=1)
    assert points.shape == (500, 3) and colours.dtype == np.uint8 and record["outliers"] > 20
    surface = trimesh.load(tmp_path / "surface.ply", force="mesh")
    _, dist, _ = trimesh.proximity.closest_point(surface, points)
    assert np.mean(dist < 0.01) > 0.85 and np.mean(dist > 0.05) > 0.02   # on it, but for the mismatches
    assert np.mean((colours[dist < 0.01] == 128).all(1)) > 0.95           # the grey photos' colour
    write_colmap_text(tmp_path / "sparse" / "0", cams, points=points, colors=colours)
    back, rgb = read_points3d(tmp_path / "sparse" / "0" / "points3D.txt")
    np.testing.assert_allclose(back, points, atol=1e-9) and np.testing.assert_allclose(rgb * 255, colours)


def test_gsplat_fit_export_reads_back_as_a_fit(tmp_path):
    """fit_gsplat's export (SH as float16) is read by fit_scenes.read_fit like any fit."""
    import numpy as np

    from experiments.fit_gsplat import export
    from experiments.fit_scenes import read_fit
    from phirie_jax.types import GaussianSplatData

    rng = np.random.default_rng(0)
    n = 9
    data = GaussianSplatData(means=rng.normal(size=(n, 3)).astype(np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                             log_scales=np.full((n, 3), -4.0, np.float32), opacity_logits=np.zeros(n, np.float32),
                             sh=rng.normal(size=(n, 16, 3)).astype(np.float32))
    export(tmp_path / "s_gsplat_default.npz", data, {"scene": "s", "steps": 3, "seed": 0, "gaussians": n})
    back = read_fit(tmp_path / "s_gsplat_default.npz")
    assert back.record["scene"] == "s" and back.gaussians.sh.dtype == np.float32
    np.testing.assert_array_equal(back.gaussians.means, data.means)
    np.testing.assert_allclose(back.gaussians.sh, data.sh, rtol=1e-3, atol=1e-3)


@pytest.mark.slow  # 22 s on 2 cores: the probe's slow per-pixel reference
def test_depth_probe_reference_two_layers():
    """A semi-transparent layer (opacity 0.4) in front of an opaque one: the probe's per-pixel
    reference gives the rasterizer's expected depth there, and its median (accumulated opacity
    first past 0.5) is the opaque layer's depth."""
    import jax.numpy as jnp
    import numpy as np
    import pytest

    from experiments.depth_probe import composite_pixel
    from kernels.gaussians import Gaussians
    from kernels.project import project_gaussians
    from kernels.raster import RasterConfig, rasterize

    K = jnp.asarray([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]], jnp.float32)
    w2c = jnp.eye(4, dtype=jnp.float32)
    g = Gaussians(means=jnp.asarray([[0.0, 0, 1.0], [0.0, 0, 1.5]], jnp.float32),
                  quats=jnp.asarray([[1.0, 0, 0, 0]] * 2, jnp.float32),
                  log_scales=jnp.full((2, 3), np.log(0.2), jnp.float32),
                  opacity_logits=jnp.asarray([np.log(0.4 / 0.6), 8.0], jnp.float32),
                  sh=jnp.zeros((2, 1, 3), jnp.float32))
    proj = project_gaussians(g, K, w2c, width=32, height=32)
    rows = [np.asarray(x, np.float64) for x in (proj.means2d, proj.conics, proj.opacities, proj.depths)]
    expected, at, alpha = composite_pixel(np.array([16.5, 16.5]), *rows)
    out = rasterize(g, K, w2c, width=32, height=32, config=RasterConfig(compositor="jax"))
    assert expected == pytest.approx(float(out.depth_normalized[16, 16]), abs=1e-4)
    assert alpha == pytest.approx(float(out.alpha[16, 16]), abs=1e-5)
    assert 1.0 < expected < 1.5 and at[0.5] == pytest.approx(1.5) and at[0.95] == pytest.approx(1.5)


def test_compile_determinism_counts_the_worlds_two_runs_agree_on(tmp_path):
    import numpy as np

    from experiments.compile_determinism import compare

    first = np.random.default_rng(0).normal(size=(5, 7)).astype(np.float32)
    second = first.copy()
    second[2, 3] = np.nextafter(second[2, 3], np.float32(np.inf))      # one ulp in one world
    np.save(tmp_path / "a.npy", first)
    np.save(tmp_path / "b.npy", second)
    result = compare(tmp_path / "a.npy", tmp_path / "b.npy")
    assert result["worlds"] == 5 and result["worlds_equal"] == 4
    assert result["max_abs_qpos_difference"] == abs(float(second[2, 3]) - float(first[2, 3])) > 0
    assert compare(tmp_path / "a.npy", tmp_path / "a.npy")["worlds_equal"] == 5
    np.save(tmp_path / "c.npy", first[:4])
    with pytest.raises(SystemExit, match="shape"):
        compare(tmp_path / "a.npy", tmp_path / "c.npy")


def test_bench_env_reads_compositor_settings_and_refuses_others():
    import argparse

    from experiments.bench_env import compositor_setting

    assert compositor_setting("8:4") == (8, 4, False)
    assert compositor_setting("16:2:prefetch") == (16, 2, True)
    for bad in ("8", "8:x", "8:4:ahead", "8:4:prefetch:1", "-8:4"):
        with pytest.raises(argparse.ArgumentTypeError, match="expected CHUNK:WARPS or CHUNK:WARPS:prefetch"):
            compositor_setting(bad)


def test_asset_mesh_benchmark_compares_the_same_arrays_and_edges(tmp_path, monkeypatch):
    """Both readers see the same numbers and both edge counts the same edges on a real asset OBJ (a
    closed box); an OBJ without the asset header is left to trimesh; a reader off by a rounding is
    caught."""
    import numpy as np
    import trimesh

    import phirie_jax.io.mesh
    from experiments.bench_asset_meshes import bench
    from phirie_jax.construct.objects.assets import write_obj

    box = trimesh.creation.box(extents=(0.1, 0.2, 0.3))
    write_obj(tmp_path / "objects" / "1" / "mesh.obj", box.vertices, box.faces)
    other = tmp_path / "objects" / "2" / "mesh.obj"
    other.parent.mkdir()
    other.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in box.vertices)
                     + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in box.faces))
    result = bench([tmp_path], repeats=1)
    assert result["meshes"] == 2 and result["triangles"] == 24 and result["repair"]["repaired"] == 2
    assert result["read"]["read_by_numpy"] == 1 and result["read"]["same_arrays_as_trimesh"]
    assert result["edge_count"]["same_edge_ids_and_counts"]

    exact = phirie_jax.io.mesh.read_asset_obj

    def rounded(path):
        arrays = exact(path)
        return None if arrays is None else (np.nextafter(arrays[0], np.inf), arrays[1])

    monkeypatch.setattr(phirie_jax.io.mesh, "read_asset_obj", rounded)
    assert not bench([tmp_path], repeats=1)["read"]["same_arrays_as_trimesh"]
