"""A mounted object (a head on a wall): welded where it is placed in ``scene.xml``, its drop test
is the hold test of the exported scene, and the same body without the weld falls."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from phirie_jax import layout
from phirie_jax.construct.physics.body import body_name, mount_name
from phirie_jax.construct.physics.config import DropTestConfig, PhysicsConfig
from phirie_jax.construct.physics.droptest import HOLD_BACKEND
from phirie_jax.construct.physics.mjcf import settle_scene
from phirie_jax.construct.physics.stage import drop_test_objects, export_scene
from phirie_jax.info import drop_verdict, status_words
from phirie_jax.manifest import Manifest
from tests.fixtures.box_scene import converted_folder

RAISED = 0.15        # m: object 3 hangs this far above the floor
HELD = 2e-3          # m: what the weld may let it sag in the drop test's 4 s
WALL = {"normal": [1.0, 0.0, 0.0], "offset": 0.05, "gap_m": 0.01, "source": "test"}
CONFIG = PhysicsConfig(drop_test=DropTestConfig(backend="mujoco"))


def _hanging(out, mounted: bool):
    """The box scene with object 3 raised ``RAISED`` (mounted on ``WALL`` or not), exported and drop-tested."""
    converted_folder(out)
    manifest = Manifest.load(out)
    objects = []
    for o in manifest.require("objects", "test"):
        if o.id == 3:
            pose = np.array(o.pose)
            pose[2, 3] += RAISED
            o = o.with_fields(pose=pose, support={"height": 0.0, "source": "surface", "gap_m": RAISED},
                              **({"mount": WALL} if mounted else {}))
        objects.append(o)
    up = np.array([0.0, 0.0, 1.0])
    export_scene(tuple(objects), up, None, out, CONFIG)
    return {o.id: o for o in drop_test_objects(tuple(objects), up, out, CONFIG)}


def test_a_mounted_object_is_welded_and_held_where_it_is_placed(tmp_path):
    objects = _hanging(tmp_path, mounted=True)
    welds = ET.parse(tmp_path / layout.SCENE_MJCF).getroot().findall("equality/weld")
    assert [(w.get("name"), w.get("body1"), w.get("body2")) for w in welds] == [
        (mount_name(body_name(3)), "world", body_name(3))]
    held = objects[3]
    assert held.drop_test["backend"] == HOLD_BACKEND and held.drop_test["stable"]
    assert held.drop_test["drift_m"] < HELD
    assert "hold test" in held.check("settling").details["method"]
    assert str(held.status) == "accepted" and status_words(held) == "accepted, mounted"
    assert drop_verdict(held).startswith("held by its weld")
    assert objects[7].drop_test["backend"] == "mujoco"          # the free object is still dropped
    assert settle_scene(tmp_path / layout.SCENE_MJCF, 2.0)[body_name(3)] < HELD


def test_without_the_weld_the_same_body_falls_in_the_exported_scene(tmp_path):
    objects = _hanging(tmp_path, mounted=False)
    assert ET.parse(tmp_path / layout.SCENE_MJCF).getroot().find("equality") is None
    assert objects[3].drop_test["backend"] == "mujoco"
    assert settle_scene(tmp_path / layout.SCENE_MJCF, 2.0)[body_name(3)] == pytest.approx(RAISED, abs=0.02)


def test_the_usd_scene_fixes_a_mounted_body_where_it_is_placed(tmp_path):
    pxr = pytest.importorskip("pxr")
    from phirie_jax.construct.physics.usd import MOUNT_JOINT
    from phirie_jax.geometry import split_sim3

    objects = _hanging(tmp_path, mounted=True)
    stage = pxr.Usd.Stage.Open(str(tmp_path / layout.SCENE_USD))
    joint = pxr.UsdPhysics.FixedJoint(stage.GetPrimAtPath(f"/World/{body_name(3)}/{MOUNT_JOINT}"))
    assert joint and joint.GetBody0Rel().GetTargets() == []                  # the world
    assert [str(t) for t in joint.GetBody1Rel().GetTargets()] == [f"/World/{body_name(3)}"]
    _, _, translation = split_sim3(np.asarray(objects[3].pose))
    np.testing.assert_allclose(np.array(joint.GetLocalPos0Attr().Get()), translation, atol=1e-6)
    assert not stage.GetPrimAtPath(f"/World/{body_name(7)}/{MOUNT_JOINT}")    # the free body has none
