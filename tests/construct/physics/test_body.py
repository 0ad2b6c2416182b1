"""One body builder: an object's body in ``scene.xml`` and in its drop-test model carry the same
inertial and contact parameters (to the 9 significant digits ``scene.xml`` writes)."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from phirie_jax import layout
from phirie_jax.construct.physics.body import body_name, object_body
from phirie_jax.construct.physics.collision import convex_part
from phirie_jax.construct.physics.config import DropTestConfig, PhysicsConfig
from phirie_jax.construct.physics.droptest import build_model, drop_body, part_bucket
from phirie_jax.construct.physics.mjcf import scene_mjcf
from phirie_jax.construct.physics.parts import read_part, write_parts
from phirie_jax.construct.physics.priors import priors
from phirie_jax.construct.physics.supports import fit_background

WRITTEN = 1e-8   # relative: scene.xml carries 9 significant digits, the drop-test model full doubles


def _tensor(model: mujoco.MjModel, body: int) -> np.ndarray:
    """(3, 3) inertia tensor about the centre of mass in the body frame, from the compiled model."""
    rot = Rotation.from_quat(model.body_iquat[body], scalar_first=True).as_matrix()
    return rot @ np.diag(model.body_inertia[body]) @ rot.T


@pytest.fixture
def exported(tmp_path):
    """One object of two convex parts with a scaled pose and non-default priors, its parts written."""
    rng = np.random.default_rng(3)
    parts = tuple(convex_part(rng.normal(size=(40, 3)) * [0.04, 0.03, 0.06] + offset, 64)
                  for offset in ([0.0, 0.0, 0.06], [0.05, 0.0, 0.02]))
    config = PhysicsConfig(friction=0.7, restitution=0.3, category_masses=(("mug", 0.45),))
    paths = write_parts(tmp_path, 7, parts)
    pose = np.eye(4)
    pose[:3, :3] = 1.5 * Rotation.from_rotvec([0.1, -0.2, 0.8]).as_matrix()
    pose[:3, 3] = [0.2, -0.1, 0.75]
    body = object_body(7, [read_part(tmp_path / p) for p in paths], pose, priors("mug", config), paths)
    return tmp_path, body, config


def test_the_scene_body_and_the_drop_test_body_carry_the_same_inertial_and_contact(exported):
    out, body, config = exported
    up = np.array([0.0, 0.0, 1.0])
    (out / layout.SCENE_MJCF).write_text(scene_mjcf([body], fit_background([], up), up, config))
    scene = mujoco.MjModel.from_xml_path(str(out / layout.SCENE_MJCF))
    drop = build_model(drop_body(body, up), part_bucket(len(body.parts), DropTestConfig()), DropTestConfig())
    s, d = scene.body(body_name(7)).id, drop.body("body").id
    assert scene.body_mass[s] == drop.body_mass[d] == pytest.approx(0.45)
    np.testing.assert_allclose(scene.body_ipos[s], drop.body_ipos[d], rtol=WRITTEN, atol=1e-12)
    np.testing.assert_allclose(_tensor(scene, s), _tensor(drop, d), rtol=WRITTEN, atol=1e-14)
    scene_geoms = np.flatnonzero(scene.geom_bodyid == s)
    drop_geoms = np.flatnonzero(drop.geom_bodyid == d)[: len(body.parts)]          # ghost parts follow
    assert len(scene_geoms) == len(drop_geoms) == 2
    for field in ("geom_friction", "geom_solref", "geom_solimp", "geom_solmix", "geom_condim", "geom_margin"):
        np.testing.assert_allclose(getattr(scene, field)[scene_geoms], getattr(drop, field)[drop_geoms],
                                   rtol=WRITTEN, err_msg=field)
    np.testing.assert_allclose(scene.geom_friction[scene_geoms[0]], [0.7, 0.005, 0.0001])
    # the same convex parts: the scene's scaled file meshes and the drop test's inline ones
    for g_s, g_d in zip(scene_geoms, drop_geoms):
        np.testing.assert_allclose(scene.geom_rbound[g_s], drop.geom_rbound[g_d], rtol=1e-6)
