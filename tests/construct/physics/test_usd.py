"""``scene.usda``: re-opened with pxr, every body's schemas, mass, inertia and parts agree with
``manifest.json`` and with ``scene.xml`` (one home for the physical values); supports are static
colliders; the stage is metric and +Z up. Without pxr nothing is written and the reason says how."""

from __future__ import annotations

import json

import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from phirie_jax import layout
from phirie_jax.construct.physics import usd
from phirie_jax.construct.physics.parts import read_part
from phirie_jax.geometry import split_sim3
from tests.fixtures.box_scene import BOXES, converted_folder

pxr = pytest.importorskip("pxr", reason="usd-core is not installed (the usd extra)")
from pxr import Usd, UsdGeom, UsdPhysics  # noqa: E402

FLOAT32_REL = 2e-6   # USD stores mass properties and points as 32-bit floats
POSE_TOL = 1e-9      # the body transform is written in double precision


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    out = converted_folder(tmp_path_factory.mktemp("usd"))
    manifest = json.loads((out / layout.MANIFEST).read_text())
    return out, manifest, Usd.Stage.Open(str(out / layout.SCENE_USD))


def test_stage_is_metric_z_up_with_gravity_down(folder):
    out, manifest, stage = folder
    assert manifest["physics"]["usd"] == {"path": layout.SCENE_USD}
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdPhysics.GetStageKilogramsPerUnit(stage) == 1.0
    assert stage.GetDefaultPrim().GetPath() == "/World"
    scenes = [p for p in stage.Traverse() if p.IsA(UsdPhysics.Scene)]
    assert len(scenes) == 1
    physics_scene = UsdPhysics.Scene(scenes[0])
    assert np.allclose(physics_scene.GetGravityDirectionAttr().Get(), (0.0, 0.0, -1.0))
    assert physics_scene.GetGravityMagnitudeAttr().Get() == pytest.approx(9.81)


def _tensor(mass_api) -> np.ndarray:
    """The full inertia tensor from USD's principal moments and axes."""
    q = mass_api.GetPrincipalAxesAttr().Get()
    axes = Rotation.from_quat([q.GetReal(), *q.GetImaginary()], scalar_first=True).as_matrix()
    return axes @ np.diag(np.asarray(mass_api.GetDiagonalInertiaAttr().Get(), np.float64)) @ axes.T


def test_every_body_matches_the_manifest_and_the_mjcf(folder):
    out, manifest, stage = folder
    model = mujoco.MjModel.from_xml_path(str(out / layout.SCENE_MJCF))
    accepted = [o for o in manifest["objects"] if o["status"] == "accepted"]
    assert {o["id"] for o in accepted} == set(BOXES)
    bodies = [p for p in stage.Traverse() if p.HasAPI(UsdPhysics.RigidBodyAPI)]
    assert sorted(p.GetName() for p in bodies) == sorted(o["physics"]["body"] for o in accepted)
    for entry in accepted:
        prim = stage.GetPrimAtPath(f"/World/{entry['physics']['body']}")
        assert prim.HasAPI(UsdPhysics.RigidBodyAPI) and prim.HasAPI(UsdPhysics.MassAPI)
        mass_api = UsdPhysics.MassAPI(prim)
        recorded = entry["physics"]["mass_properties"]
        assert mass_api.GetMassAttr().Get() == pytest.approx(entry["mass"], rel=FLOAT32_REL)
        assert mass_api.GetMassAttr().Get() == pytest.approx(recorded["mass"], rel=FLOAT32_REL)
        assert np.allclose(mass_api.GetCenterOfMassAttr().Get(), recorded["com"], rtol=FLOAT32_REL, atol=1e-8)
        inertia = np.asarray(recorded["inertia"])
        assert np.allclose(_tensor(mass_api), inertia, rtol=0, atol=1e-5 * np.abs(inertia).max())
        # the same values MuJoCo reads from scene.xml
        body = model.body(entry["physics"]["body"])
        assert mass_api.GetMassAttr().Get() == pytest.approx(float(body.mass[0]), rel=FLOAT32_REL)
        assert np.allclose(np.sort(mass_api.GetDiagonalInertiaAttr().Get()), np.sort(body.inertia),
                           rtol=1e-5)
        # placed at the pose's rotation and translation; parts in the scaled body frame
        scale, rotation, translation = split_sim3(np.asarray(entry["pose"]))
        world = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default())).T
        assert np.allclose(world[:3, :3], rotation, atol=POSE_TOL) and np.allclose(world[:3, 3], translation,
                                                                                    atol=POSE_TOL)
        parts = [p for p in Usd.PrimRange(prim) if p.HasAPI(UsdPhysics.CollisionAPI)]
        assert len(parts) == len(entry["collision"])
        for part_prim, path in zip(sorted(parts, key=lambda p: p.GetName()), entry["collision"]):
            assert part_prim.HasAPI(UsdPhysics.MeshCollisionAPI)
            approximation = UsdPhysics.MeshCollisionAPI(part_prim).GetApproximationAttr().Get()
            assert approximation == UsdPhysics.Tokens.convexHull
            assert UsdGeom.Imageable(part_prim).GetPurposeAttr().Get() == UsdGeom.Tokens.guide
            points = np.asarray(UsdGeom.Mesh(part_prim).GetPointsAttr().Get(), np.float64)
            assert np.allclose(points, scale * read_part(out / path).vertices, atol=1e-6)
        visual = stage.GetPrimAtPath(f"/World/{entry['physics']['body']}/visual")
        assert visual.IsA(UsdGeom.Mesh) and not visual.HasAPI(UsdPhysics.CollisionAPI)


def test_supports_are_static_colliders(folder):
    out, manifest, stage = folder
    supports = [p for p in Usd.PrimRange(stage.GetPrimAtPath("/World/supports"))
                if p.HasAPI(UsdPhysics.CollisionAPI)]
    assert [p.GetName() for p in supports] == [g["name"] for g in manifest["physics"]["background"]]
    for prim in supports:
        assert not any(a.HasAPI(UsdPhysics.RigidBodyAPI) for a in (prim, prim.GetParent()))


def test_without_pxr_nothing_is_written_and_the_reason_says_how(folder, monkeypatch, tmp_path):
    out, _, _ = folder
    stale = tmp_path / layout.SCENE_USD
    stale.write_text("#usda 1.0\n")
    monkeypatch.setattr(usd, "usd_available", lambda: False)
    record = usd.write_scene_usd(tmp_path, [], [], [], np.array([0.0, 0.0, 1.0]), None)
    assert record["path"] is None and "pip install" in record["reason"] and "usd-core" in record["reason"]
    assert not stale.exists()  # an earlier run's scene.usda would no longer describe scene.xml
