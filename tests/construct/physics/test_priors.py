"""Mass properties against trimesh and closed forms, their group properties, and the priors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from phirie_jax.construct.physics.collision import ConvexPart, convex_part
from phirie_jax.construct.physics.config import PhysicsConfig
from phirie_jax.construct.physics.priors import (
    CATEGORY_MATERIALS,
    Shape,
    damping_ratio,
    mass_properties,
    prior_mass,
    priors,
)

RTOL = 1e-9


def part_of(mesh) -> ConvexPart:
    return ConvexPart(np.asarray(mesh.vertices, float), np.asarray(mesh.faces))


def test_box_matches_the_closed_form():
    a, b, c, m = 0.1, 0.2, 0.3, 0.3
    box = trimesh.creation.box([a, b, c])
    box.apply_translation([0.01, -0.02, 0.15])
    props = mass_properties([part_of(box)], m)
    assert props.volume == pytest.approx(a * b * c, rel=RTOL)
    np.testing.assert_allclose(props.com, [0.01, -0.02, 0.15], atol=1e-12)
    expected = m / 12 * np.diag([b * b + c * c, a * a + c * c, a * a + b * b])
    np.testing.assert_allclose(props.inertia, expected, rtol=RTOL, atol=1e-15)


def test_random_convex_parts_match_trimesh():
    rng = np.random.default_rng(3)
    for _ in range(5):
        part = convex_part(rng.normal(size=(40, 3)) * [0.05, 0.03, 0.08] + rng.normal(size=3) * 0.1, 64)
        ref = trimesh.Trimesh(part.vertices, part.faces)
        props = mass_properties([part], 0.3)
        ref.density = 0.3 / ref.volume
        assert props.volume == pytest.approx(ref.volume, rel=RTOL)
        np.testing.assert_allclose(props.com, ref.center_mass, atol=1e-12)
        np.testing.assert_allclose(props.inertia, ref.moment_inertia, rtol=1e-7, atol=1e-14)


def test_two_halves_equal_the_whole():
    whole = trimesh.creation.box([0.2, 0.1, 0.05])
    left, right = trimesh.creation.box([0.1, 0.1, 0.05]), trimesh.creation.box([0.1, 0.1, 0.05])
    left.apply_translation([-0.05, 0, 0])
    right.apply_translation([0.05, 0, 0])
    a = mass_properties([part_of(whole)], 0.3)
    b = mass_properties([part_of(left), part_of(right)], 0.3)
    np.testing.assert_allclose(b.com, a.com, atol=1e-12)
    np.testing.assert_allclose(b.inertia, a.inertia, rtol=RTOL, atol=1e-15)


def test_scale_and_rotation_act_as_they_should():
    cone = part_of(trimesh.creation.cone(0.04, 0.12, sections=20))
    base = mass_properties([cone], 0.3)
    scaled = mass_properties([cone], 0.3, scale=2.0)
    np.testing.assert_allclose(scaled.com, 2 * base.com, atol=1e-12)
    np.testing.assert_allclose(scaled.inertia, 4 * base.inertia, rtol=RTOL, atol=1e-15)   # same mass, I ∝ s²
    assert scaled.density == pytest.approx(base.density / 8, rel=RTOL)
    rot = Rotation.from_rotvec([0.3, -1.1, 0.4]).as_matrix()
    turned = mass_properties([ConvexPart(cone.vertices @ rot.T, cone.faces)], 0.3)
    np.testing.assert_allclose(turned.inertia, rot @ base.inertia @ rot.T, rtol=1e-9, atol=1e-15)
    moments, axes = base.principal()
    assert np.linalg.det(axes) == pytest.approx(1.0)
    np.testing.assert_allclose(axes @ np.diag(moments) @ axes.T, base.inertia, atol=1e-15)


def test_an_empty_body_is_refused():
    with pytest.raises(ValueError, match="no volume"):
        mass_properties([], 0.3)


def test_restitution_maps_to_a_damping_ratio_that_rebounds_with_it():
    assert damping_ratio(0.0) == 1.0
    for e in (0.05, 0.3, 0.7, 0.95):
        zeta = damping_ratio(e)
        assert 0 < zeta < 1
        assert math.exp(-math.pi * zeta / math.sqrt(1 - zeta**2)) == pytest.approx(e, rel=1e-12)
    assert damping_ratio(0.2) > damping_ratio(0.6)             # less bounce, more damping


def test_priors_default_to_the_paper_and_take_the_category_table():
    p = priors(None)
    assert (p.mass, p.friction, p.restitution, p.solref) == (0.3, 0.5, 0.0, (0.02, 1.0))
    config = PhysicsConfig(category_masses=(("mug", 0.35), ("box", 0.1)))
    assert priors("mug", config).mass == 0.35 and "mug" in priors("mug", config).mass_source
    assert priors("bottle", config).mass == 0.3
    assert priors(None, PhysicsConfig(mass=1.2)).mass == 1.2


def test_a_solids_mass_is_its_density_times_its_hull_volume():
    can = trimesh.creation.cylinder(radius=0.0335, height=0.101, sections=256)
    shape = Shape.of_mesh(can.vertices, can.faces)
    assert shape.hull_volume == pytest.approx(math.pi * 0.0335 ** 2 * 0.101, rel=1e-3)
    mass, source = prior_mass("can", PhysicsConfig(), shape)
    # YCB's 349 g soup can has the same size: the table gives it back
    assert mass == pytest.approx(0.349, rel=0.03) and source.startswith("category can: 977 kg/m³ × ")
    double = Shape.of_mesh(can.vertices, can.faces, scale=2.0)
    assert prior_mass("can", PhysicsConfig(), double)[0] == pytest.approx(8 * mass)   # mass grows with volume


def test_a_shells_mass_follows_its_wall_area_not_its_volume():
    mug = trimesh.creation.annulus(r_min=0.036, r_max=0.040, height=0.095, sections=256)
    shape = Shape.of_mesh(mug.vertices, mug.faces)
    material = CATEGORY_MATERIALS["mug"]
    mass, source = prior_mass("mug", PhysicsConfig(), shape)
    assert mass == pytest.approx(material.density * material.thickness * shape.area / 2)
    assert 0.15 < mass < 0.4 and "5 mm" in source          # a stoneware mug's few hundred grams
    bowl_16cm = trimesh.creation.annulus(r_min=0.075, r_max=0.080, height=0.06, sections=256)
    assert prior_mass("bowl", PhysicsConfig(), Shape.of_mesh(bowl_16cm.vertices, bowl_16cm.faces))[0] > mass


def test_the_mass_comes_from_the_most_specific_source():
    box = trimesh.creation.box((0.06, 0.16, 0.21))
    shape = Shape.of_mesh(box.vertices, box.faces)
    config = PhysicsConfig(category_masses=(("box", 0.5),), object_masses=((7, 0.9),))
    assert prior_mass("box", config, shape, object_id=7) == (0.9, "given (--mass 7=0.9)")
    assert prior_mass("box", config, shape, object_id=8) == (0.5, "category table (box)")
    assert prior_mass("box", PhysicsConfig(), shape)[0] == pytest.approx(178 * 0.06 * 0.16 * 0.21)
    assert prior_mass("Cracker Box", PhysicsConfig(), shape)[0] == pytest.approx(178 * 0.06 * 0.16 * 0.21)
    assert prior_mass("teapot", PhysicsConfig(), shape) == (0.3, "config (paper default 0.3 kg)")
    assert prior_mass("box", PhysicsConfig(), None) == (0.3, "config (paper default 0.3 kg)")   # no shape known
