"""Observation at a working width: a photo wider than it is ray cast on the working image's
grid (bounded rays), each pixel taking the nearest cast ray's hit; narrower photos are cast
as they are."""

from __future__ import annotations

import numpy as np
import trimesh

from phirie_jax.observe.raycast import Raycaster, pixel_grid, working_pixel_grid
from tests.observe.helpers import ring

AGREE = 0.95  # fraction of pixels whose nearest-ray depth matches the exact one (edges differ)


def test_grid_is_unchanged_up_to_the_working_width_and_bounded_past_it():
    for w, h in ((640, 480), (320, 240), (64, 48)):
        for stride in (1, 2, 3):
            for a, b in zip(working_pixel_grid(w, h, stride, 640), pixel_grid(w, h, stride)):
                np.testing.assert_array_equal(a, b)
    rows, cols = working_pixel_grid(4032, 3024, 2, 640)
    assert len(cols) == 320 and len(rows) == 240
    assert rows.max() < 3024 and cols.max() < 4032 and np.all(np.diff(cols) > 0)


def test_cast_camera_past_the_working_width_matches_the_full_cast():
    box = trimesh.creation.box((0.3, 0.2, 0.15))
    cam = ring(1, 0.8, 0.4, width=256, height_px=192, focal=220.0)[0]
    full = Raycaster(box.vertices, box.faces).depth_map(cam)
    working = Raycaster(box.vertices, box.faces, working_width=64).depth_map(cam)
    assert working.shape == full.shape == (192, 256)
    same = np.isclose(working, full, atol=0.01)
    assert same.mean() > AGREE
    np.testing.assert_array_equal(Raycaster(box.vertices, box.faces, working_width=256).depth_map(cam), full)
