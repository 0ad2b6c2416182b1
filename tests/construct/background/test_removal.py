"""R_asset takes the Gaussians near the placed asset's surface and those inside it (an optimizer
puts Gaussians deep inside large objects), and nothing outside its reach."""

from __future__ import annotations

import numpy as np
import trimesh

from phirie_jax.construct.background.removal import near_surface


def test_near_or_inside_the_asset_and_nothing_beyond():
    box = trimesh.creation.box(extents=[0.3, 0.3, 0.3])
    rng = np.random.default_rng(0)
    inside = rng.uniform(-0.1, 0.1, (200, 3))                    # ≥ 5 cm inside every face
    shell = np.column_stack([np.full(50, 0.16), rng.uniform(-0.1, 0.1, (50, 2))])   # 1 cm outside
    outside = np.column_stack([np.full(50, 0.2), rng.uniform(-0.1, 0.1, (50, 2))])  # 5 cm outside
    far = rng.uniform(1.0, 2.0, (50, 3))
    means = np.concatenate([inside, shell, outside, far])
    taken = near_surface(means, box.vertices, box.faces, radius=0.024)
    np.testing.assert_array_equal(taken, np.arange(250))
