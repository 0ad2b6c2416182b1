"""R_asset takes the Gaussians near the placed asset's surface and those inside it (an optimizer
puts Gaussians deep inside large objects), and nothing outside its reach."""

from __future__ import annotations

import numpy as np
import trimesh

from phirie_jax.construct.background.removal import near_surface
from phirie_jax.observe.raycast import Raycaster


def test_near_or_inside_the_asset_and_nothing_beyond():
    box = trimesh.creation.box(extents=[0.3, 0.3, 0.3])
    rng = np.random.default_rng(0)
    inside = rng.uniform(-0.1, 0.1, (200, 3))                    # ≥ 5 cm inside every face
    shell = np.column_stack([np.full(50, 0.16), rng.uniform(-0.1, 0.1, (50, 2))])   # 1 cm outside
    outside = np.column_stack([np.full(50, 0.2), rng.uniform(-0.1, 0.1, (50, 2))])  # 5 cm outside
    far = rng.uniform(1.0, 2.0, (50, 3))
    means = np.concatenate([inside, shell, outside, far])
    taken = near_surface(means, Raycaster(box.vertices, box.faces), radius=0.024)
    np.testing.assert_array_equal(taken, np.arange(250))


def _needles(centres: np.ndarray, axes: np.ndarray, long_sigma: float, short_sigma: float = 0.001):
    """Gaussians elongated along the unit ``axes`` (N, 3)."""
    from scipy.spatial.transform import Rotation

    from phirie_jax.types import GaussianSplatData

    n = len(centres)
    rot = np.stack([Rotation.align_vectors([a], [[1.0, 0, 0]])[0].as_matrix() for a in axes])
    quats = Rotation.from_matrix(rot).as_quat(scalar_first=True) * 3.0   # stored unnormalized
    return GaussianSplatData(means=centres.astype(np.float32), quats=quats.astype(np.float32),
                             log_scales=np.tile(np.log([long_sigma, short_sigma, short_sigma]), (n, 1)).astype(np.float32),
                             opacity_logits=np.zeros(n, np.float32), sh=np.zeros((n, 1, 3), np.float32))


def test_needles_reaching_into_the_asset_across_the_contact():
    """R_reach: a needle centred on the support 4 cm from a box, its 2σ end 1 cm inside the box, is
    taken; the same needle pointing away, one falling short, and a flat support disk under the box's
    edge (in the contact plane, never deep inside) stay."""
    from phirie_jax.construct.background.removal import reaching_into

    box = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    box.apply_translation([0, 0, 0.05])                       # standing on z = 0, faces at x = ±0.05
    into = np.array([1.0, 0, 0.25])
    into /= np.linalg.norm(into)
    centres = np.array([[-0.09, 0, 0.0], [-0.09, 0, 0.0], [-0.09, 0, 0.0], [-0.03, 0.0, 0.0]])
    axes = np.array([into, [-1.0, 0, 0], into, [1.0, 0, 0]])
    reach_in = (0.05 + 0.01) / 2 / into[0]                     # 2σ ends 1 cm past the face at x = −0.05
    data = _needles(centres, axes, reach_in)
    short = _needles(centres[2:3], axes[2:3], 0.02 / 2 / into[0])       # 2σ ends 2 cm short of the face
    flat = _needles(centres[3:4], axes[3:4], 0.03)
    from phirie_jax.types import GaussianSplatData

    data = GaussianSplatData.join([data.subset(np.arange(2)), short, flat], like=data)
    taken = reaching_into(data, np.arange(data.num), Raycaster(box.vertices, box.faces), sigmas=2.0, depth=0.005)
    np.testing.assert_array_equal(taken, [0])


def test_the_inside_of_an_open_container_is_walled_in():
    """R_enclosed: the floor of a ring-walled cup (a tube standing on z = 0, its foot at the floor's
    height) is walled in; a point outside it, or between two parallel walls (a handle's gap), is not."""
    from phirie_jax.construct.background.removal import enclosed_by

    tube = trimesh.creation.annulus(r_min=0.035, r_max=0.04, height=0.1)
    tube.apply_translation([0, 0, 0.05])
    walls = trimesh.util.concatenate([trimesh.creation.box([0.1, 0.01, 0.1]).apply_translation([0.3, 0.02, 0.05]),
                                      trimesh.creation.box([0.1, 0.01, 0.1]).apply_translation([0.3, -0.02, 0.05])])
    mesh = trimesh.util.concatenate([tube, walls])
    means = np.array([[0.0, 0.0, 0.0], [0.01, -0.01, 0.03], [0.1, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, 0.0, 0.2]])
    caster = Raycaster(mesh.vertices, mesh.faces)
    walled = enclosed_by(means, np.arange(len(means)), caster, np.array([0, 0, 1.0]), 8, 0.01)
    np.testing.assert_array_equal(walled, [0, 1])
    long_up = np.array([0.0, 0.0, 2.0])                  # up of any length
    np.testing.assert_array_equal(enclosed_by(means, np.arange(len(means)), caster, long_up, 8, 0.01), [0, 1])
