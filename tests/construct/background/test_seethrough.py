"""Fill cells the cameras saw through: past a support's edge a camera sees the floor behind a cell
and votes it out; on the support, and where something hides the cell, no camera does."""

from __future__ import annotations

import numpy as np
import pytest

from phirie_jax.construct.background.seethrough import see_through_votes
from phirie_jax.construct.background.views import CropRenderer
from phirie_jax.io.camera import intrinsics_matrix
from phirie_jax.synthetic.scene import look_at
from phirie_jax.types import Camera, GaussianSplatData

SPACING = 0.01
EDGE = 0.0          # the support (z = 0) ends at x = EDGE; the floor lies 0.4 m below
FLOOR = -0.4


def _flat(xy: np.ndarray, z: float) -> GaussianSplatData:
    """Opaque flat grey Gaussians on the plane at height ``z``, σ = the grid spacing."""
    n = len(xy)
    sigma = np.log([SPACING, SPACING, 0.1 * SPACING])
    return GaussianSplatData(means=np.column_stack([xy, np.full(n, z)]).astype(np.float32),
                             quats=np.tile([1.0, 0, 0, 0], (n, 1)).astype(np.float32),
                             log_scales=np.tile(sigma, (n, 1)).astype(np.float32),
                             opacity_logits=np.full(n, 4.0, np.float32), sh=np.zeros((n, 1, 3), np.float32))


def _grid(x0, x1, y0, y1, step):
    x, y = np.meshgrid(np.arange(x0, x1, step), np.arange(y0, y1, step), indexing="ij")
    return np.column_stack([x.ravel(), y.ravel()])


def _cameras() -> tuple[Camera, ...]:
    K = intrinsics_matrix(80.0, 80.0, 48.0, 36.0)
    eyes = [(0.6, 0.0, 0.5), (0.5, 0.3, 0.6), (0.5, -0.3, 0.6), (0.08, 0.05, 0.9)]
    return tuple(Camera(f"{k}.png", K, look_at(np.array(e), np.array([0.0, 0.0, 0.0])), 96, 72)
                 for k, e in enumerate(eyes))


@pytest.fixture(scope="module")
def edge_scene():
    support = _flat(_grid(-0.4, EDGE, -0.3, 0.3, SPACING), 0.0)
    floor = _flat(_grid(-0.6, 1.2, -0.8, 0.8, 2 * SPACING), FLOOR)
    data = GaussianSplatData.join([support, floor], like=support)
    cells = np.column_stack([_grid(-0.1, 0.1, -0.05, 0.05, 0.02), np.zeros(50)])
    return data, cells


def test_cells_past_the_edge_are_seen_through_and_cells_on_the_support_are_not(edge_scene):
    data, cells = edge_scene
    (votes,) = see_through_votes(data, _cameras(), [cells], CropRenderer(),
                                 max_views=8, crop_size=64, depth_tolerance=0.02)
    on_support = cells[:, 0] < EDGE - SPACING
    in_air = cells[:, 0] > EDGE + SPACING
    assert votes.views == (0, 1, 2, 3)
    assert np.all(votes.through[on_support] == 0), votes.through[on_support]
    assert np.all(votes.through[in_air] >= 2), votes.through[in_air]
    assert np.all(votes.seen >= votes.through)


def test_a_cell_hidden_by_something_in_front_gets_no_vote(edge_scene):
    """A lid 10 cm above the cells past the edge hides them from every camera above."""
    data, cells = edge_scene
    lid = _flat(_grid(-0.02, 0.3, -0.3, 0.3, SPACING), 0.1)
    covered = GaussianSplatData.join([data, lid], like=data)
    cameras = _cameras()[3:]   # from above
    (votes,) = see_through_votes(covered, cameras, [cells], CropRenderer(),
                                 max_views=8, crop_size=64, depth_tolerance=0.02)
    assert votes.through.sum() == 0
    (open_votes,) = see_through_votes(data, cameras, [cells], CropRenderer(),
                                      max_views=8, crop_size=64, depth_tolerance=0.02)
    assert open_votes.through[cells[:, 0] > EDGE + SPACING].min() == 1


def test_views_holding_too_few_cells_do_not_vote(edge_scene):
    data, cells = edge_scene
    far_away = Camera("away.png", intrinsics_matrix(80.0, 80.0, 48.0, 36.0),
                      look_at(np.array([0.0, 0.0, 0.9]), np.array([5.0, 0.0, 0.0])), 96, 72)
    (votes,) = see_through_votes(data, (far_away,), [cells], CropRenderer(),
                                 max_views=8, crop_size=64, depth_tolerance=0.02)
    assert votes.views == () and votes.through.sum() == 0 and votes.seen.sum() == 0
