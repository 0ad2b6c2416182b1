"""Quaternions, covariances and Sim(3) transforms of Gaussians, tested by property."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kernels.gaussians import (
    Gaussians,
    Sim3,
    concatenate,
    covariance,
    quat_multiply,
    quat_to_rotmat,
    rotmat_to_quat,
    transform_bodies,
    transform_gaussians,
)
from kernels.sh import eval_sh

EXACT_F64 = 1e-10
FD_STEP = 1e-6
FD_TOL = 1e-6


def random_sim3(seed, dtype=jnp.float64) -> Sim3:
    rng = np.random.default_rng(seed)
    xyzw = Rotation.random(random_state=seed).as_quat()
    return Sim3(
        quat=jnp.asarray(np.roll(xyzw, 1), dtype),
        translation=jnp.asarray(rng.normal(size=3), dtype),
        scale=jnp.asarray(rng.uniform(0.3, 3.0), dtype),
    )


def random_gaussians(seed, n=32, degree=3, dtype=jnp.float64) -> Gaussians:
    rng = np.random.default_rng(seed)
    return Gaussians(
        means=jnp.asarray(rng.normal(size=(n, 3)), dtype),
        quats=jnp.asarray(rng.normal(size=(n, 4)) * 2.0, dtype),  # deliberately not unit
        log_scales=jnp.asarray(rng.normal(-3, 0.5, size=(n, 3)), dtype),
        opacity_logits=jnp.asarray(rng.normal(size=n), dtype),
        sh=jnp.asarray(rng.normal(size=(n, (degree + 1) ** 2, 3)), dtype),
    )


def test_quaternion_matrix_agrees_with_scipy(x64):
    q = Rotation.random(16, random_state=1).as_quat()  # xyzw
    ours = quat_to_rotmat(jnp.asarray(np.roll(q, 1, axis=1)) * 3.0)
    np.testing.assert_allclose(ours, Rotation.from_quat(q).as_matrix(), atol=EXACT_F64)


def test_quaternion_product_is_matrix_product(x64):
    a = jnp.asarray(np.roll(Rotation.random(8, random_state=2).as_quat(), 1, axis=1))
    b = jnp.asarray(np.roll(Rotation.random(8, random_state=3).as_quat(), 1, axis=1))
    np.testing.assert_allclose(
        quat_to_rotmat(quat_multiply(a, b)), quat_to_rotmat(a) @ quat_to_rotmat(b), atol=EXACT_F64
    )


def test_matrix_to_quaternion_round_trip_including_half_turns(x64):
    rots = [Rotation.random(32, random_state=4).as_matrix()]
    for axis in np.eye(3):  # 180° about each axis: the cases that break naive formulas
        rots.append(Rotation.from_rotvec(np.pi * axis).as_matrix()[None])
    rots.append(Rotation.from_rotvec([np.pi - 1e-9, 0, 0]).as_matrix()[None])
    rots.append(np.eye(3)[None])
    m = jnp.asarray(np.concatenate(rots))
    q = rotmat_to_quat(m)
    np.testing.assert_allclose(jnp.linalg.norm(q, axis=-1), 1.0, atol=EXACT_F64)
    assert bool(jnp.all(q[:, 0] >= 0))
    np.testing.assert_allclose(quat_to_rotmat(q), m, atol=1e-9)


def test_covariance_is_r_s_st_rt(x64):
    g = random_gaussians(5)
    rot = Rotation.from_quat(np.roll(np.asarray(g.quats), -1, axis=1)).as_matrix()
    s = np.exp(np.asarray(g.log_scales))
    expected = np.einsum("nij,nj,nkj->nik", rot, s**2, rot)
    np.testing.assert_allclose(covariance(g.log_scales, g.quats), expected, atol=EXACT_F64)


def test_sim3_identity_inverse_compose(x64):
    a, b, c = random_sim3(6), random_sim3(7), random_sim3(8)
    pts = jnp.asarray(np.random.default_rng(9).normal(size=(20, 3)))
    ident = Sim3.identity(jnp.float64)
    np.testing.assert_allclose(ident.apply(pts), pts, atol=EXACT_F64)
    np.testing.assert_allclose(a.compose(a.inverse()).apply(pts), pts, atol=EXACT_F64)
    np.testing.assert_allclose(a.inverse().compose(a).apply(pts), pts, atol=EXACT_F64)
    np.testing.assert_allclose(a.compose(b).apply(pts), a.apply(b.apply(pts)), atol=EXACT_F64)
    np.testing.assert_allclose(
        a.compose(b).compose(c).as_matrix(), a.compose(b.compose(c)).as_matrix(), atol=EXACT_F64
    )
    np.testing.assert_allclose(
        a.compose(b).as_matrix(), a.as_matrix() @ b.as_matrix(), atol=EXACT_F64
    )
    round_trip = Sim3.from_matrix(a.as_matrix())
    np.testing.assert_allclose(round_trip.as_matrix(), a.as_matrix(), atol=EXACT_F64)
    homog = jnp.concatenate([pts, jnp.ones((20, 1))], axis=1) @ a.as_matrix().T
    np.testing.assert_allclose(a.apply(pts), homog[:, :3], atol=EXACT_F64)


def test_transform_moves_means_and_covariances_exactly(x64):
    g, t = random_gaussians(10), random_sim3(11)
    moved = transform_gaussians(g, t)
    rot = np.asarray(t.rotation)
    s = float(t.scale)
    np.testing.assert_allclose(moved.means, t.apply(g.means), atol=EXACT_F64)
    expected = s**2 * np.einsum("ij,njk,lk->nil", rot, np.asarray(g.covariances()), rot)
    np.testing.assert_allclose(moved.covariances(), expected, atol=EXACT_F64)
    np.testing.assert_array_equal(moved.opacity_logits, g.opacity_logits)


def test_transformed_covariance_matches_transformed_samples(x64):
    """Statistical: samples of N(μ, Σ) pushed through the Sim(3) have covariance Σ'."""
    g, t = random_gaussians(12, n=3), random_sim3(13)
    moved = transform_gaussians(g, t)
    rng = np.random.default_rng(14)
    num_samples = 200_000
    for i in range(3):
        cov = np.asarray(g.covariances()[i])
        x = rng.multivariate_normal(np.asarray(g.means[i]), cov, size=num_samples)
        y = np.asarray(t.apply(jnp.asarray(x)))
        target = np.asarray(moved.covariances()[i])
        # standard error of an empirical covariance entry ≈ sqrt((Σii Σjj + Σij²)/n)
        d = np.sqrt(np.diag(target))
        stderr = np.sqrt((np.outer(d, d) ** 2 + target**2) / num_samples)
        assert np.all(np.abs(np.cov(y.T) - target) < 6 * stderr)
        assert np.all(np.abs(y.mean(0) - np.asarray(moved.means[i])) < 6 * d / np.sqrt(num_samples))


def test_transform_rotates_view_dependent_colour(x64):
    g, t = random_gaussians(15, n=8), random_sim3(16)
    moved = transform_gaussians(g, t)
    dirs = np.random.default_rng(17).normal(size=(8, 3))
    dirs = jnp.asarray(dirs / np.linalg.norm(dirs, axis=1, keepdims=True))
    np.testing.assert_allclose(
        eval_sh(moved.sh, dirs), eval_sh(g.sh, dirs @ t.rotation), atol=EXACT_F64
    )


def test_transform_group_action(x64):
    g, a, b = random_gaussians(18), random_sim3(19), random_sim3(20)
    lhs = transform_gaussians(transform_gaussians(g, b), a)
    rhs = transform_gaussians(g, a.compose(b))
    for x, y in zip(jax.tree.leaves(lhs), jax.tree.leaves(rhs)):
        if x.shape[-1] == 4:  # quaternions: compare as rotations (sign-free)
            x, y = quat_to_rotmat(x), quat_to_rotmat(y)
        np.testing.assert_allclose(x, y, atol=1e-9)


def test_transform_jacobian_matches_finite_differences(x64):
    g = random_gaussians(21, n=4, degree=2)
    t = random_sim3(22)

    @jax.jit
    def flat_out(params):
        quat, translation, log_scale = params[:4], params[4:7], params[7]
        moved = transform_gaussians(g, Sim3(quat, translation, jnp.exp(log_scale)))
        return jnp.concatenate([moved.means.ravel(), moved.log_scales.ravel(), moved.sh.ravel()])

    x0 = jnp.concatenate([t.quat, t.translation, jnp.log(t.scale)[None]])
    jac = jax.jacfwd(flat_out)(x0)
    fd = np.stack(
        [
            (flat_out(x0.at[i].add(FD_STEP)) - flat_out(x0.at[i].add(-FD_STEP))) / (2 * FD_STEP)
            for i in range(x0.size)
        ],
        axis=1,
    )
    np.testing.assert_allclose(jac, fd, atol=FD_TOL, rtol=FD_TOL)
    np.testing.assert_allclose(jax.jacrev(flat_out)(x0), jac, atol=EXACT_F64)


def test_batched_transforms_under_vmap_and_jit():
    g = random_gaussians(23, n=16, dtype=jnp.float32)
    ts = jax.tree.map(lambda *xs: jnp.stack(xs), *[random_sim3(s, jnp.float32) for s in range(5)])
    batched = jax.jit(jax.vmap(transform_gaussians, in_axes=(None, 0)))(g, ts)
    assert batched.means.shape == (5, 16, 3)
    assert batched.sh.shape == (5, 16, 16, 3)
    one = transform_gaussians(g, jax.tree.map(lambda x: x[3], ts))
    np.testing.assert_allclose(batched.means[3], one.means, atol=1e-5)


def test_pytree_is_frozen_and_replaceable():
    g = random_gaussians(24, n=2, dtype=jnp.float32)
    with pytest.raises(AttributeError):
        g.means = g.means  # type: ignore[misc]
    h = g.replace(opacity_logits=g.opacity_logits + 1)
    assert h.num == 2 and h.sh_degree == 3
    assert len(jax.tree.leaves(h)) == 5


def test_per_body_transforms_match_one_transform_per_set(x64):
    g = random_gaussians(25, n=12)
    a, b = random_sim3(26), random_sim3(27)
    transforms = jax.tree.map(lambda x, y: jnp.stack([x, y]), a, b)
    body = jnp.array([0, 1] * 6)
    moved = transform_bodies(g, transforms, body)
    for k, t in enumerate((a, b)):
        sub = jax.tree.map(lambda x: x[k::2], g)
        ref = transform_gaussians(sub, t)
        for x, y in zip(jax.tree.leaves(jax.tree.map(lambda x: x[k::2], moved)), jax.tree.leaves(ref)):
            np.testing.assert_allclose(x, y, atol=EXACT_F64)
    # degree 0 (no band matrix): the colours are left as they are
    flat = g.replace(sh=g.sh[:, :1])
    np.testing.assert_array_equal(transform_bodies(flat, transforms, body).sh, flat.sh)
    both = concatenate([g, g])
    assert both.num == 24 and both.sh.shape == (24, 16, 3)


def test_concatenate_joins_host_sets_on_the_host_and_device_sets_on_the_device():
    parts = [random_gaussians(seed, n=n, degree=1, dtype=jnp.float32) for seed, n in ((0, 5), (1, 7))]
    on_device = concatenate(parts)
    on_host = concatenate([jax.tree.map(np.asarray, g) for g in parts])
    assert all(isinstance(x, np.ndarray) for x in jax.tree.leaves(on_host))
    assert all(isinstance(x, jax.Array) for x in jax.tree.leaves(on_device))
    assert on_host.num == on_device.num == 12
    for a, b in zip(jax.tree.leaves(on_host), jax.tree.leaves(on_device)):
        np.testing.assert_array_equal(a, np.asarray(b))
