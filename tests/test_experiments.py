"""Experiments import the package as it is installed (no ``sys.path`` edits) and run as modules
from the project root (``python -m experiments.NAME``)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

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
    assert np.array_equal(capture_to_world({}), np.eye(4))
    cams = tuple(Camera(f"{k:04d}.jpg", camera.K, w2c, 64, 48) for k in range(17))
    train, held = held_out_split(cams, 8)
    assert [c.name for c in held] == ["0000.jpg", "0008.jpg", "0016.jpg"] and len(train) == 14
