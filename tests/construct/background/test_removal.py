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


def test_the_support_is_spared_away_from_the_contact_only():
    """support_outside_contact: a Gaussian at most the band above the support (or below it) and
    farther than the reach, across up, from the object's contact is the support's own; one near the
    contact, or higher up, is not. The object's points well above the support are no contact."""
    from phirie_jax.construct.background.removal import support_outside_contact

    angle = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    rim = np.column_stack([0.03 * np.cos(angle), 0.03 * np.sin(angle), np.full(64, 0.004)])   # the contact
    brim = np.column_stack([0.2 * np.cos(angle), 0.2 * np.sin(angle), np.full(64, 0.08)])    # an overhang
    obj = np.concatenate([rim, brim])
    means = np.array([
        [0.035, 0.0, 0.0],     # 5 mm from the contact, on the support: taken
        [0.0, 0.0, 0.002],     # inside the contact ring: taken
        [0.06, 0.0, 0.0],      # 3 cm out, on the support: spared
        [0.2, 0.0, 0.0],       # under the overhang, on the support: spared
        [0.06, 0.0, -0.03],    # 3 cm out, below the support (a sagging duvet): spared
        [0.06, 0.0, 0.02],     # 3 cm out, 2 cm up: not the support
    ])
    spared = support_outside_contact(means, np.arange(6), obj, np.array([0.0, 0, 1]), 0.0, band=0.01, reach=0.01)
    np.testing.assert_array_equal(spared, [2, 3, 4])
    tilted = np.array([0.0, np.sin(0.2), np.cos(0.2)])   # the same scene turned: the same answer
    from phirie_jax.geometry import rotation_to_z

    turn = rotation_to_z(tilted).T
    np.testing.assert_array_equal(
        support_outside_contact(means @ turn.T, np.arange(6), obj @ turn.T, tilted, 0.0, band=0.01, reach=0.01),
        [2, 3, 4])


def test_what_views_saw_outside_the_mask_is_given_back_except_at_the_contact():
    """spared_sets: a Gaussian the mask views saw outside the mask is given back, but not one where
    the object meets its support (it straddles the masks' edge: left, it is a ghost of the object's
    rim), and never one the object carries; the support away from the contact is given back."""
    from phirie_jax.construct.background.config import BackgroundConfig
    from phirie_jax.construct.background.removal import spared_sets

    angle = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    rim = np.column_stack([0.03 * np.cos(angle), 0.03 * np.sin(angle), np.full(64, 0.006)])   # the contact
    means = np.array([
        [0.031, 0.0, 0.001],   # the object's rim on the support, seen outside the masks: taken
        [0.0, 0.05, 0.05],     # a floater beside it, 5 cm up, seen outside the masks: given back
        [0.06, 0.0, 0.0],      # the support 3 cm out, not seen: given back as the support
        [0.0, 0.032, 0.0015],  # rim, seen outside the masks, but carried by the object: taken
        [0.0, 0.0, 0.04],      # the object itself, not seen elsewhere: taken
    ])
    config = BackgroundConfig()
    union, seen, own = np.arange(5), np.array([0, 1, 3]), np.array([3])
    r_seen, spared = spared_sets(means, union, seen, own, (0.0, rim), np.array([0.0, 0, 1]), config)
    np.testing.assert_array_equal(r_seen, [1])
    np.testing.assert_array_equal(spared, [2])
    r_seen, spared = spared_sets(means, union, seen, own, None, np.array([0.0, 0, 1]), config)
    np.testing.assert_array_equal(r_seen, [0, 1])   # without a contact nothing marks the rim
    assert len(spared) == 0
    # a soft support's own surface at the contact but away from the placed asset is given back
    r_seen, _ = spared_sets(means, union, seen, own, (0.0, rim), np.array([0.0, 0, 1]), config,
                            near_asset=lambda idx: np.isin(idx, [3, 4]))
    np.testing.assert_array_equal(r_seen, [0, 1])
    r_seen, _ = spared_sets(means, union, seen, own, (0.0, rim), np.array([0.0, 0, 1]), config,
                            near_asset=lambda idx: np.isin(idx, [0, 3, 4]))
    np.testing.assert_array_equal(r_seen, [1])


def test_a_view_votes_what_it_saw_outside_the_mask():
    """_job_votes: a centre visible on the instance's mask votes for R_mask; one visible off the
    mask votes *elsewhere* (it is something else, spared from R_obs and R_asset); one behind what
    the view rendered at its pixel votes for neither."""
    from pathlib import Path

    from phirie_jax.construct.background.config import BackgroundConfig
    from phirie_jax.construct.background.removal import MaskJob, _job_votes
    from phirie_jax.construct.background.views import CropImage, make_crop
    from phirie_jax.io.camera import intrinsics_matrix
    from phirie_jax.types import Camera

    camera = Camera("0.png", intrinsics_matrix(50.0, 50.0, 32.0, 32.0), np.eye(4), 64, 64)
    crop = make_crop(camera, 0, np.array([0, 0, 63, 63]), (64,), 0)
    mask = np.zeros((64, 64), np.int64)
    mask[:, :32] = 7                                        # the instance fills the left half
    depth = np.full((64, 64), 1.0, np.float32)
    image = CropImage(np.zeros((64, 64, 3), np.float32), np.ones((64, 64), np.float32), depth,
                      np.zeros((64, 64, 1), np.float32))
    means = np.array([[-0.2, 0.0, 1.0],    # on the mask, at the rendered depth
                      [0.2, 0.0, 1.0],     # off the mask, at the rendered depth
                      [0.2, 0.1, 1.5],     # off the mask, 0.5 behind what the view saw
                      [-0.2, 0.1, 1.5]])   # on the mask, behind
    job = MaskJob(0, 0, 7, Path("mask.png"), crop)
    in_view, in_mask, elsewhere = _job_votes(means, np.arange(4), job, mask, image, (camera,), BackgroundConfig())
    np.testing.assert_array_equal(in_view, [True, False, False, False])
    np.testing.assert_array_equal(in_mask, [True, False, False, True])
    np.testing.assert_array_equal(elsewhere, [False, True, False, False])
