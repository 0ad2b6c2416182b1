"""Densification on the device (kernels.densify) against the host reference
(phirie_jax.capture.densify.densify_and_prune), and its invariants."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kernels import densify, splat_fit
from phirie_jax.capture.config import TrainConfig
from phirie_jax.capture.densify import (
    children_noise,
    densify_and_prune,
    densify_limits,
    densify_on_device,
    padded,
    unpadded,
)
from phirie_jax.render import gaussian_bucket
from phirie_jax.types import GaussianSplatData

RULE = TrainConfig(grad_threshold=2e-4, percent_dense=0.01, min_opacity=0.005, max_scale=0.1)


def random_set(rng, n: int, degree_coeffs: int = 4) -> GaussianSplatData:
    """n Gaussians spread over the thresholds: some small, some large, some transparent, some huge."""
    sigma = np.exp(rng.uniform(np.log(1e-3), np.log(0.3), size=(n, 3)))
    return GaussianSplatData(
        means=rng.normal(size=(n, 3)).astype(np.float32), quats=rng.normal(size=(n, 4)).astype(np.float32),
        log_scales=np.log(sigma).astype(np.float32), opacity_logits=rng.uniform(-8, 4, size=n).astype(np.float32),
        sh=rng.normal(size=(n, degree_coeffs, 3)).astype(np.float32))


def moments_of(params, rng):
    """A stand-in optimizer state: two per-Gaussian trees of random moments and a scalar count."""
    def rand(x):
        return jnp.asarray(rng.normal(size=x.shape).astype(np.float32))
    return (jax.tree.map(rand, params), jax.tree.map(rand, params), jnp.int32(7))


@pytest.mark.parametrize("prune_large", [True, False])
@pytest.mark.parametrize("max_gaussians", [2_000_000, 230])
def test_device_densification_equals_the_host_reference(prune_large, max_gaussians):
    rng = np.random.default_rng(3)
    n, size = 200, 256
    data = random_set(rng, n)
    grad_sum = np.zeros(size, np.float32)
    seen = np.zeros(size, np.float32)
    seen[:n] = rng.integers(0, 5, size=n)
    grad_sum[:n] = seen[:n] * rng.uniform(0, 4e-4, size=n).astype(np.float32)
    grad_sum[n - 20:n] = seen[n - 20] * 3e-4  # ties: the lower row goes first
    rule = dataclasses.replace(RULE, max_gaussians=max_gaussians)
    params, valid = padded(data, size)
    state = moments_of(params, rng)
    key = jax.random.key(11)

    out, out_valid, out_state, counts = densify_on_device(params, valid, state, jnp.asarray(grad_sum),
                                                          jnp.asarray(seen), 2.0, rule, key, prune_large)
    noise = np.asarray(children_noise(key, size))[:, :n]
    grad = grad_sum[:n] / np.maximum(seen[:n], 1.0)
    want, source, want_counts = densify_and_prune(data, grad, 2.0, rule, noise, prune_large=prune_large)

    assert counts == {"count": want.num, **want_counts}
    assert counts["cloned"] + counts["split"] > 0 and counts["pruned"] > 0
    assert out.num == gaussian_bucket(want.num)
    assert np.array_equal(np.asarray(out_valid), np.arange(out.num) < want.num)
    got = unpadded(out, out_valid)
    for field in ("quats", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(got, field), getattr(want, field), err_msg=field)
    np.testing.assert_allclose(got.log_scales, want.log_scales, rtol=0, atol=1e-6)
    np.testing.assert_allclose(got.means, want.means, rtol=0, atol=1e-5)
    # the kept rows keep their moments, the new ones start at zero; the count passes through
    for tree, original_tree in zip(out_state[:2], state[:2]):
        for leaf, original in zip(jax.tree.leaves(tree), jax.tree.leaves(original_tree)):
            leaf, original = np.asarray(leaf)[:want.num], np.asarray(original)
            expected = np.where((source >= 0).reshape((-1,) + (1,) * (leaf.ndim - 1)), original[np.maximum(source, 0)],
                                0.0)
            np.testing.assert_array_equal(leaf, expected)
    assert int(out_state[2]) == 7
    # padding rows are transparent
    assert (np.asarray(out.opacity_logits)[want.num:] == splat_fit.PAD_OPACITY_LOGIT).all()


def test_children_are_drawn_from_their_parent():
    """A split Gaussian's children: offsets R (z ⊙ s) (so, in its own frame, z ⊙ s) and scales s / 1.6."""
    rng = np.random.default_rng(5)
    data = random_set(rng, 8)
    params, _ = padded(data, 8)
    noise = jnp.asarray(rng.normal(size=(2, 8, 3)).astype(np.float32))
    children = np.asarray(densify.children_means(params, noise))
    from kernels.gaussians import quat_to_rotmat
    rot = np.asarray(quat_to_rotmat(params.quats))
    local = np.einsum("sji,csj->csi", rot, children - np.asarray(params.means)[None])  # Rᵀ (child − mean)
    np.testing.assert_allclose(local, np.asarray(noise) * np.exp(data.log_scales)[None], rtol=1e-4, atol=1e-6)


def test_nothing_chosen_and_nothing_pruned_changes_nothing():
    rng = np.random.default_rng(2)
    data = random_set(rng, 200)
    data = dataclasses.replace(data, opacity_logits=np.full(200, 3.0, np.float32),
                               log_scales=np.full((200, 3), np.log(0.01), np.float32))
    params, valid = padded(data, gaussian_bucket(200))
    state = moments_of(params, rng)
    out, out_valid, out_state, counts = densify_on_device(params, valid, state, jnp.zeros(params.num),
                                                          jnp.ones(params.num), 1.0, RULE, jax.random.key(0))
    assert counts == {"count": 200, "cloned": 0, "split": 0, "pruned": 0}
    for a, b in zip(jax.tree.leaves((out, out_valid)), jax.tree.leaves((params, valid))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    for a, b in zip(jax.tree.leaves(out_state[:2]), jax.tree.leaves(state[:2])):  # padding's moments: zero
        np.testing.assert_array_equal(np.asarray(a)[:200], np.asarray(b)[:200])


def test_the_plan_never_exceeds_the_room():
    """max_gaussians caps growth: the count after densifying is at most the cap (before pruning)."""
    rng = np.random.default_rng(9)
    data = dataclasses.replace(random_set(rng, 120), opacity_logits=np.full(120, 3.0, np.float32))
    params, valid = padded(data, 128)
    for cap in (100, 120, 125, 10_000):
        rule = dataclasses.replace(RULE, max_gaussians=cap, max_scale=10.0)
        plan = densify.plan(params, valid, jnp.full(128, 1.0), densify_limits(rule, 1.0, True))
        assert int(plan.count) == max(120, min(cap, 240)) and int(plan.pruned) == 0
