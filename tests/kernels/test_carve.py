"""Visual-hull carving: one view against a per-voxel loop, and the hull of a sphere seen by a
ring of cameras contains the sphere and stays close to it."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from kernels.carve import CARVE, INSIDE, NO_VOTE, carve, view_votes
from phirie_jax.io.camera import intrinsics_matrix
from phirie_jax.synthetic.scene import look_at

W, H = 96, 80
FOCAL = 90.0
RADIUS = 0.1


def ring_cameras(n=8, radius=0.8, height=0.4):
    K = intrinsics_matrix(FOCAL, FOCAL, W / 2, H / 2)
    cams = []
    for a in np.linspace(0, 2 * np.pi, n, endpoint=False):
        eye = np.array([radius * np.cos(a), radius * np.sin(a), height])
        cams.append((K, look_at(eye, np.zeros(3))))
    return cams


def sphere_state(K, w2c):
    """Per-pixel state of a sphere at the origin: INSIDE where the pixel-centre ray hits it."""
    c2w = np.linalg.inv(w2c)
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    dirs = np.stack([jj, ii, np.ones_like(jj)], -1) @ np.linalg.inv(K).T @ c2w[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    o = c2w[:3, 3]
    b = dirs @ o
    hit = b * b - (o @ o - RADIUS**2) >= 0
    return np.where(hit, INSIDE, CARVE).astype(np.uint8)


def reference_votes(centres, K, w2c, state):
    keep, carve_votes = np.zeros(len(centres), int), np.zeros(len(centres), int)
    for i, p in enumerate(centres):
        c = w2c[:3, :3] @ p + w2c[:3, 3]
        if c[2] <= 1e-6:
            continue
        u = K[0, 0] * c[0] / c[2] + K[0, 1] * c[1] / c[2] + K[0, 2]
        v = K[1, 1] * c[1] / c[2] + K[1, 2]
        col, row = int(np.floor(u)), int(np.floor(v))
        if 0 <= col < W and 0 <= row < H:
            keep[i] = state[row, col] == INSIDE
            carve_votes[i] = state[row, col] == CARVE
    return keep, carve_votes


def test_view_votes_match_a_per_voxel_loop():
    rng = np.random.default_rng(0)
    K, w2c = ring_cameras()[1]
    state = rng.choice([CARVE, INSIDE, NO_VOTE], size=(H, W)).astype(np.uint8)
    centres = rng.uniform(-0.5, 0.5, (500, 3))
    keep, carve_votes = view_votes(jnp.asarray(centres, jnp.float32), jnp.asarray(K, jnp.float32),
                                   jnp.asarray(w2c, jnp.float32), jnp.asarray(state))
    ref_keep, ref_carve = reference_votes(centres, K, w2c, state)
    assert np.mean(np.asarray(keep) == ref_keep) > 0.99      # float32 vs float64 at pixel borders
    assert np.mean(np.asarray(carve_votes) == ref_carve) > 0.99
    assert np.asarray(keep).sum() > 0 and np.asarray(carve_votes).sum() > 0


def test_hull_of_a_sphere_contains_it_and_padded_views_change_nothing():
    cams = ring_cameras()
    g = np.linspace(-0.15, 0.15, 31)
    centres = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    Ks = np.stack([k for k, _ in cams])
    w2c = np.stack([m for _, m in cams])
    states = np.stack([sphere_state(k, m) for k, m in cams])
    keep, carved = carve(jnp.asarray(centres, jnp.float32), jnp.asarray(Ks, jnp.float32),
                         jnp.asarray(w2c, jnp.float32), jnp.asarray(states))
    hull = (np.asarray(carved) == 0) & (np.asarray(keep) >= 2)
    r = np.linalg.norm(centres, axis=1)
    pixel = np.hypot(0.8, 0.4) / FOCAL                       # a pixel's footprint at the sphere
    assert np.all(hull[r < RADIUS - pixel])                  # the object is never carved (masks are
                                                             # pixel-discrete: allow one pixel)
    assert not np.any(hull[r > 2.0 * RADIUS])                # and the hull stays near it
    assert hull.sum() < 2.0 * np.sum(r < RADIUS)
    pad = np.full((3, H, W), NO_VOTE, np.uint8)
    keep2, carved2 = carve(jnp.asarray(centres, jnp.float32), jnp.asarray(np.concatenate([Ks, Ks[:3]]), jnp.float32),
                           jnp.asarray(np.concatenate([w2c, w2c[:3]]), jnp.float32),
                           jnp.asarray(np.concatenate([states, pad])))
    np.testing.assert_array_equal(np.asarray(keep2), np.asarray(keep))
    np.testing.assert_array_equal(np.asarray(carved2), np.asarray(carved))


def test_an_object_cut_by_the_image_border_in_most_views_is_not_carved():
    """Real captures frame objects loosely: in 6 of 8 views the sphere's centre projects onto the
    image's left edge (half of it out of frame). Out-of-image voxels get no vote, so the hull
    still holds the whole sphere."""
    cams = ring_cameras()
    shifted = intrinsics_matrix(FOCAL, FOCAL, 0.0, H / 2)    # the optical axis at the left edge
    cams = [(shifted if k % 4 else K, m) for k, (K, m) in enumerate(cams)]
    g = np.linspace(-0.15, 0.15, 31)
    centres = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    states = np.stack([sphere_state(k, m) for k, m in cams])
    cut = [k for k, (K, m) in enumerate(cams) if (states[k] == INSIDE)[:, 0].any()]
    assert len(cut) == 6                                      # the mask touches the border there
    keep, carved = carve(jnp.asarray(centres, jnp.float32), jnp.asarray(np.stack([k for k, _ in cams]), jnp.float32),
                         jnp.asarray(np.stack([m for _, m in cams]), jnp.float32), jnp.asarray(states))
    hull = (np.asarray(carved) == 0) & (np.asarray(keep) >= 2)
    r = np.linalg.norm(centres, axis=1)
    pixel = np.hypot(0.8, 0.4) / FOCAL
    assert np.all(hull[r < RADIUS - pixel])
    assert not np.any(hull[r > 1.6 * RADIUS])                # the two full views and the halves still bound it
