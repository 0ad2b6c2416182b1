"""observe → objects → physics on a small tabletop, the physics stage in MJX (slow: builds a
scene, registers candidates and compiles the MJX program of each part bucket)."""

from __future__ import annotations

import json

import mujoco
import pytest

from kernels.registration import SearchSpec
from phirie_jax.construct.objects.config import ObjectsConfig, RegistrationConfig
from phirie_jax.construct.objects.stage import run_objects
from phirie_jax.construct.physics.config import DropTestConfig, PhysicsConfig
from phirie_jax.construct.physics.settling import candidate_settler
from phirie_jax.construct.physics.stage import run_physics
from phirie_jax.io.ply import write_gaussian_ply
from phirie_jax.observe.config import ObserveConfig
from phirie_jax.observe.stage import run_observe
from tests.observe.helpers import tabletop_folder

pytestmark = pytest.mark.slow

FAST_OBJECTS = ObjectsConfig(hull_resolution=32, registration=RegistrationConfig(search=SearchSpec(
    model_points=4096, sweep_model_points=256, sweep_obs_points=256, icp_model_points=1024, icp_obs_points=1024,
    score_obs_points=1024), hypothesis_batch=108))
SETTLE_LIMIT = 0.03


def test_constructed_objects_become_a_loadable_scene_with_drop_tests(tmp_path):
    root = tmp_path / "scene"
    scene, _, _ = tabletop_folder(root, num_cameras=10, width=200, height=150)
    write_gaussian_ply(root / "point_cloud.ply", scene.capture.data)
    out = tmp_path / "out"
    run_observe(root, out, ObserveConfig(pixel_stride=1, mask_erosion_px=1), masks="files")
    run_objects(root, out, FAST_OBJECTS, settle=candidate_settler())
    manifest = run_physics(root, out, PhysicsConfig(drop_test=DropTestConfig(backend="mjx")))
    on_disk = json.loads((out / "manifest.json").read_text())
    assert on_disk["objects"] == manifest["objects"]
    accepted = [o for o in manifest["objects"] if o["status"] == "accepted"]
    assert accepted, "the object stage accepted nothing"
    model = mujoco.MjModel.from_xml_path(str(out / "scene.xml"))
    assert {f"object_{o['id']}" for o in accepted} <= {model.body(b).name for b in range(model.nbody)}
    moved = manifest["physics"]["scene_settle"]["displacement_m"]
    for obj in accepted:
        assert obj["drop_test"]["backend"] == "mjx" and obj["drop_test"]["error"] is None
        assert obj["checks"]["settling"]["passed"] == obj["drop_test"]["stable"]
        if obj["drop_test"]["stable"]:
            assert moved[f"object_{obj['id']}"] < SETTLE_LIMIT
