"""The plane step's prefilters: the ring, the fill region and the neighbour colours computed from
the Gaussians of a box around the object equal the same computations over every kept Gaussian."""

from __future__ import annotations

import numpy as np
import pytest

from phirie_jax.construct.background import plane as fill_mod
from phirie_jax.construct.background.config import BackgroundConfig

UP = np.array([0.05, -0.03, 1.0]) / np.linalg.norm([0.05, -0.03, 1.0])   # a slightly tilted table


@pytest.fixture(scope="module")
def tabletop():
    """Kept Gaussians of a 1.2 m tabletop (with a hole under the object), a few above and below it,
    and a 6 cm cylinder's surface points standing on it."""
    rng = np.random.default_rng(3)
    from phirie_jax.geometry import rotation_to_z

    to_world = rotation_to_z(UP).T
    xy = rng.uniform(-0.6, 0.6, (60_000, 2))
    xy = xy[np.hypot(xy[:, 0] - 0.1, xy[:, 1]) > 0.03]
    table = np.column_stack([xy, rng.normal(0, 0.001, len(xy))])
    clutter = rng.uniform([-0.6, -0.6, -0.2], [0.6, 0.6, 0.3], (5_000, 3))
    kept = np.concatenate([table, clutter]) @ to_world.T
    angle = rng.uniform(0, 2 * np.pi, 3000)
    height = rng.uniform(0, 0.12, 3000)
    obj = np.column_stack([0.1 + 0.03 * np.cos(angle), 0.03 * np.sin(angle), height]) @ to_world.T
    removed = obj[:500] + rng.normal(0, 0.002, (500, 3))
    return kept, rng.uniform(0.3, 1.0, len(kept)), rng.uniform(0, 1, (len(kept), 3)), obj, removed


def _everything(points, lo, hi, index=None):
    return np.arange(len(points))


def _plane_step(tabletop, config, indexed=False):
    kept, opacity, rgb, obj, removed = tabletop
    index = fill_mod.BoxIndex(kept) if indexed else None
    ring = fill_mod.ring_points(kept, opacity, obj, UP, 0.0, config, index)
    plane, reason = fill_mod.fit_plane(kept[ring], UP, config, np.zeros(3))
    assert plane is not None, reason
    region = fill_mod.fill_region(plane, kept, opacity, obj, removed, config, index)
    on_plane = np.abs(plane.height(kept)) <= config.fill.slab
    colours = fill_mod.neighbour_colours(region.centres, kept[on_plane], rgb[on_plane], config.fill.colour_neighbours)
    return ring, region, colours


def test_prefiltered_plane_step_equals_the_step_over_every_gaussian(tabletop, monkeypatch):
    config = BackgroundConfig()
    ring, region, colours = _plane_step(tabletop, config)
    assert len(ring) > 100 and region.num > 10 and region.exposed > 0
    ring_ix, region_ix, colours_ix = _plane_step(tabletop, config, indexed=True)   # the objects' shared index
    np.testing.assert_array_equal(ring_ix, ring)
    np.testing.assert_array_equal(region_ix.centres, region.centres)
    np.testing.assert_array_equal(colours_ix, colours)
    monkeypatch.setattr(fill_mod, "within_box", _everything)
    ring_all, region_all, colours_all = _plane_step(tabletop, config)
    np.testing.assert_array_equal(ring, ring_all)
    np.testing.assert_array_equal(region.centres, region_all.centres)
    assert (region.exposed, region.covered_spacing) == (region_all.exposed, region_all.covered_spacing)
    np.testing.assert_array_equal(colours, colours_all)


def test_neighbour_colours_fall_back_to_every_gaussian_when_the_box_is_too_small():
    rng = np.random.default_rng(0)
    far = rng.uniform(-1, 1, (200, 3)) + [0.5, 0, 0]            # the nearest are beyond the reach
    centres = np.zeros((3, 3))
    rgb = rng.uniform(0, 1, (200, 3))
    order = np.argsort(np.linalg.norm(far, axis=1))[:8]
    got = fill_mod.neighbour_colours(centres, far, rgb, 8)
    np.testing.assert_allclose(got, np.broadcast_to(rgb[order].mean(0), (3, 3)))


def test_box_index_finds_what_testing_every_point_finds():
    from phirie_jax.construct.background.plane import BoxIndex, within_box
    from phirie_jax.construct.background.removal import _in_box

    rng = np.random.default_rng(4)
    points = np.round(rng.uniform(-1, 1, (5000, 3)), 2)   # ties on x and points on the boxes' faces
    index = BoxIndex(points)
    for _ in range(50):
        lo = np.round(rng.uniform(-1.2, 1, 3), 2)
        hi = lo + np.round(rng.uniform(0, 0.6, 3), 2)
        box = np.stack([lo, hi])
        expected = np.flatnonzero(np.all((points >= lo) & (points <= hi), axis=1))
        np.testing.assert_array_equal(index.within(lo, hi), expected)
        np.testing.assert_array_equal(_in_box(points, box, index), _in_box(points, box))
        np.testing.assert_array_equal(within_box(points, lo, hi, index), within_box(points, lo, hi))
    assert len(index.within(np.full(3, 2.0), np.full(3, 3.0))) == 0


def test_a_guessed_base_past_the_edge_lays_no_fill_in_the_air():
    """A table ending at x = 0.145 and an object at its edge whose shape (an extrusion down to the
    support) has a base reaching 8 cm past the edge: with that base as
    evidence of the plane the fill covers it in the air; with the observed points alone it stays
    on the table."""
    rng = np.random.default_rng(5)
    config = BackgroundConfig()
    xy = rng.uniform([-0.4, -0.4], [0.145, 0.4], (40_000, 2))
    xy = xy[np.hypot(xy[:, 0] - 0.1, xy[:, 1]) > 0.04]                 # unseen under the object
    kept = np.column_stack([xy, rng.normal(0, 0.001, len(xy))])
    opacity = np.full(len(kept), 0.9)
    angle = rng.uniform(0, 2 * np.pi, 2000)
    observed = np.column_stack([0.1 + 0.04 * np.cos(angle), 0.04 * np.sin(angle), rng.uniform(0.002, 0.1, 2000)])
    base_grid = np.stack(np.meshgrid(np.arange(0.06, 0.23, 0.004), np.arange(-0.04, 0.04, 0.004)), -1).reshape(-1, 2)
    guessed_base = np.column_stack([base_grid, np.zeros(len(base_grid))])
    obj = np.concatenate([observed, guessed_base])
    plane = fill_mod.Plane(np.zeros(3), np.array([0.0, 0, 1]), len(kept), len(kept), 0.001)
    removed = observed[:300]
    trusting = fill_mod.fill_region(plane, kept, opacity, obj, removed, config)
    observed_only = fill_mod.fill_region(plane, kept, opacity, obj, removed, config, contact_points=observed)
    past_edge = 0.145 + config.fill.margin + config.fill.grid
    assert (trusting.centres[:, 0] > past_edge).sum() > 50
    assert (observed_only.centres[:, 0] > past_edge).sum() == 0
    assert observed_only.num > 100   # the unseen table under the object is still filled
