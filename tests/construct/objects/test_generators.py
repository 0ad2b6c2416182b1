"""Built-in generators on observed points of known shapes; the gravity frame and supports."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from phirie_jax.construct.objects.candidates import builtin, mesh_problem
from phirie_jax.construct.objects.config import ObjectsConfig
from phirie_jax.construct.objects.generators import InstanceInput, extrude, primitive
from phirie_jax.frame.gravity import GravityFrame, gravity_frame
from phirie_jax.geometry import rotation_to_z
from phirie_jax.observe.raycast import Raycaster
from phirie_jax.observe.support import Support, find_support
from tests.kernels.shapes import box_surface

SUPPORT_Z = 0.75
CONFIG = ObjectsConfig()


def instance(points, support=SUPPORT_Z):
    frame = gravity_frame(np.array([0.0, 0.0, 1.0]), "test")
    return InstanceInput(1, points, frame, Support(support, "surface", 100, np.array([0.0, 0.0, 1.0])), (), (), ())


def observed_box(size, rng, yaw=0.4, n=4000):
    pts, normals = box_surface((-size[0] / 2, -size[1] / 2, 0.0), size, n, rng)
    seen = normals[:, 2] > -0.5  # everything but the bottom
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    return pts[seen] @ rot.T + [0.1, -0.2, SUPPORT_Z]


def placed(shape):
    return trimesh.Trimesh(shape.vertices + shape.placement[:3, 3], shape.faces, process=True)


def test_primitive_fits_an_upright_box_and_a_cylinder():
    rng = np.random.default_rng(0)
    shape = primitive(instance(observed_box((0.12, 0.06, 0.18), rng)), CONFIG)
    assert shape.info["kind"] == "box"
    assert sorted(shape.info["size"][:2]) == pytest.approx([0.06, 0.12], abs=0.003)
    assert shape.info["size"][2] == pytest.approx(0.18, abs=0.004)
    mesh = placed(shape)
    assert mesh.is_watertight and mesh.bounds[0, 2] == pytest.approx(SUPPORT_Z, abs=1e-6)
    np.testing.assert_allclose(shape.vertices.min(0)[2], 0.0, atol=1e-9)  # canonical: base at the origin
    a = rng.uniform(0, 2 * np.pi, 3000)
    z = rng.uniform(0, 0.1, 3000)
    cyl = np.column_stack([0.3 + 0.035 * np.cos(a), 0.035 * np.sin(a), SUPPORT_Z + z])
    shape = primitive(instance(cyl), CONFIG)
    assert shape.info["kind"] == "cylinder" and shape.info["radius"] == pytest.approx(0.035, abs=0.001)


def test_extrude_closes_a_box_down_to_its_support():
    rng = np.random.default_rng(1)
    shape = extrude(instance(observed_box((0.10, 0.08, 0.06), rng, n=20000)), CONFIG)
    mesh = placed(shape)
    assert mesh.is_watertight and mesh.volume > 0
    assert mesh.volume == pytest.approx(0.10 * 0.08 * 0.06, rel=0.2)
    assert mesh.bounds[0, 2] == pytest.approx(SUPPORT_Z, abs=0.003)
    assert mesh.bounds[1, 2] == pytest.approx(SUPPORT_Z + 0.06, abs=0.006)


def test_a_generator_that_cannot_work_gives_a_failed_candidate():
    flat = np.column_stack([np.random.default_rng(2).random((200, 2)), np.full(200, SUPPORT_Z)])
    c = builtin("extrude", instance(flat), CONFIG, 0)
    assert not c.ok and "above the support" in c.error
    c = builtin("visual_hull", instance(flat), CONFIG, 0)
    assert not c.ok and "view" in c.error
    assert mesh_problem(np.zeros((3, 3)), np.zeros((0, 3), np.int64)).startswith("no triangles")
    assert "non-finite" in mesh_problem(np.full((3, 3), np.nan), np.array([[0, 1, 2]]))


def test_rotation_to_z_and_the_support_of_a_tilted_table_in_its_gravity_frame():
    rng = np.random.default_rng(3)
    for _ in range(5):
        up = rng.normal(size=3)
        up /= np.linalg.norm(up)
        r = rotation_to_z(up)
        np.testing.assert_allclose(r @ up, [0, 0, 1], atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0)
    tilt = np.radians(4.0)
    true_up = np.array([np.sin(tilt), 0.0, np.cos(tilt)])
    table = trimesh.creation.box(extents=[2.0, 2.0, 0.02])
    table.apply_translation([0, 0, -0.01])
    table.apply_transform(np.vstack([np.column_stack([rotation_to_z(true_up).T, [0, 0, 0.5]]), [0, 0, 0, 1]]))
    caster = Raycaster(table.vertices, table.faces)
    q_g = observed_box((0.08, 0.08, 0.1), rng) - [0.1, -0.2, SUPPORT_Z - 0.5]   # standing on the table at 0.5
    q_world = q_g @ rotation_to_z(true_up)                                        # the table is tilted
    frame = gravity_frame(true_up, "given")
    support = find_support(frame.to_gravity(q_world), frame, caster)
    assert support.source == "surface" and support.hits > 20
    assert np.degrees(np.arccos(support.normal @ [0, 0, 1])) < 0.2   # the plane fit sees the table level
    assert support.height == pytest.approx(true_up @ [0, 0, 0.5], abs=1e-3)  # the plane through (0, 0, 0.5)
    nothing = find_support(frame.to_gravity(q_world), frame, None)
    assert nothing.source == "observed points"
    assert isinstance(frame, GravityFrame)


def test_a_support_is_a_plane_only_when_enough_rays_found_it():
    up = np.array([0.0, 0.0, 1.0])
    assert Support(0.75, "surface", 400, up).is_plane
    assert not Support(0.75, "surface", 4, up).is_plane            # a plaque's edge under a wall-mounted head
    assert not Support(0.75, "observed points", 0, up).is_plane
    record = Support(0.75, "surface", 400, up).as_record()
    assert Support.from_record(record).height == 0.75 and Support.from_record(record).hits == 400
