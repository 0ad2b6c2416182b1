"""SH evaluation and rotation, tested by their mathematical properties."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kernels.sh import (
    SH_C0,
    eval_sh,
    num_sh_coeffs,
    rgb_to_sh_dc,
    rotate_sh,
    rotate_sh_bands,
    sh_band_rotations,
    sh_basis,
    sh_degree_from_coeffs,
    sh_to_rgb,
)

ROTATION_TOL_F64 = 1e-10
ROTATION_TOL_F32 = 1e-5
QUADRATURE_TOL = 2e-3  # Fibonacci-sphere integration error with 200K points


def random_unit(rng, n):
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def fibonacci_sphere(n):
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = np.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def test_basis_is_orthonormal_on_the_sphere():
    """∫ Y_i Y_j dΩ = δ_ij catches any wrong constant, sign-independent."""
    d = fibonacci_sphere(200_000)
    basis = sh_basis(d, 3)
    gram = basis.T @ basis * (4 * np.pi / len(d))
    np.testing.assert_allclose(gram, np.eye(16), atol=QUADRATURE_TOL)


def test_basis_matches_3dgs_sign_convention():
    """Degree-1 terms are (−C1 y, C1 z, −C1 x) as in the INRIA implementation."""
    b = sh_basis(np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]), 1)
    c1 = 0.4886025119029199
    np.testing.assert_allclose(b[:, 1:], [[0, 0, -c1], [-c1, 0, 0], [0, c1, 0]])
    np.testing.assert_allclose(b[:, 0], SH_C0)


def test_dc_colour_round_trip_and_clamp():
    rgb = jnp.array([0.2, 0.5, 0.9])
    sh = jnp.zeros((4, 3)).at[0].set(rgb_to_sh_dc(rgb))
    np.testing.assert_allclose(sh_to_rgb(sh, jnp.array([0.0, 0.6, 0.8])), rgb, atol=1e-6)
    dark = jnp.full((1, 3), -10.0)
    assert float(jnp.min(sh_to_rgb(dark, jnp.array([0.0, 0.0, 1.0])))) == 0.0


@pytest.mark.parametrize("degree", [1, 2, 3])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rotation_float64(x64, degree, seed):
    rng = np.random.default_rng(seed)
    rot = jnp.asarray(Rotation.random(random_state=seed).as_matrix())
    coeffs = jnp.asarray(rng.normal(size=(num_sh_coeffs(degree), 3)))
    dirs = jnp.asarray(random_unit(rng, 64))
    rotated = rotate_sh(coeffs, rot)
    lhs = eval_sh(jnp.broadcast_to(rotated, (64,) + rotated.shape), dirs)
    rhs = eval_sh(jnp.broadcast_to(coeffs, (64,) + coeffs.shape), dirs @ rot)  # rows Rᵀd
    np.testing.assert_allclose(lhs, rhs, atol=ROTATION_TOL_F64)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_rotation_float32_batched_under_jit(degree):
    rng = np.random.default_rng(10 + degree)
    rots = jnp.asarray(Rotation.random(8, random_state=degree).as_matrix(), jnp.float32)
    coeffs = jnp.asarray(rng.normal(size=(8, 32, num_sh_coeffs(degree), 3)), jnp.float32)
    dirs = jnp.asarray(random_unit(rng, 8 * 32).reshape(8, 32, 3), jnp.float32)
    rotated = jax.jit(jax.vmap(rotate_sh))(coeffs, rots)
    lhs = eval_sh(rotated, dirs)
    rhs = eval_sh(coeffs, jnp.einsum("bpi,bij->bpj", dirs, rots))
    np.testing.assert_allclose(lhs, rhs, atol=ROTATION_TOL_F32)


def test_rotation_group_properties(x64):
    rng = np.random.default_rng(3)
    c = jnp.asarray(rng.normal(size=(16, 3)))
    r1 = jnp.asarray(Rotation.random(random_state=4).as_matrix())
    r2 = jnp.asarray(Rotation.random(random_state=5).as_matrix())
    np.testing.assert_allclose(rotate_sh(c, jnp.eye(3)), c, atol=ROTATION_TOL_F64)
    np.testing.assert_allclose(
        rotate_sh(rotate_sh(c, r1), r2), rotate_sh(c, r2 @ r1), atol=ROTATION_TOL_F64
    )
    np.testing.assert_allclose(rotate_sh(rotate_sh(c, r1), r1.T), c, atol=ROTATION_TOL_F64)
    # each band's energy is invariant (the band rotation matrices are orthogonal)
    rotated = rotate_sh(c, r1)
    for lo, hi in [(1, 4), (4, 9), (9, 16)]:
        np.testing.assert_allclose(
            jnp.sum(rotated[lo:hi] ** 2), jnp.sum(c[lo:hi] ** 2), rtol=1e-10
        )
    np.testing.assert_array_equal(rotated[0], c[0])


def test_band_matrices_built_once_rotate_each_set_as_its_own_rotation(x64):
    """Band matrices of 3 rotations, gathered for 40 coefficient sets: each set rotated as
    ``rotate_sh`` rotates it by its own rotation, and each band the matrix product W_l c_l
    (a loop reference); a wrong number of bands is refused."""
    rng = np.random.default_rng(12)
    rots = jnp.asarray(Rotation.random(3, random_state=12).as_matrix())
    body = rng.integers(0, 3, 40)
    coeffs = jnp.asarray(rng.normal(size=(40, 16, 3)))
    bands = sh_band_rotations(rots, 3)
    got = rotate_sh_bands(coeffs, tuple(w[body] for w in bands))
    np.testing.assert_allclose(got, jax.vmap(rotate_sh)(coeffs, rots[body]), atol=ROTATION_TOL_F64)
    for n in range(40):
        for band, w in enumerate(bands, start=1):
            lo, hi = band * band, (band + 1) ** 2
            np.testing.assert_allclose(got[n, lo:hi], np.asarray(w[body[n]]) @ np.asarray(coeffs[n, lo:hi]),
                                       atol=1e-12)
    with pytest.raises(ValueError, match="2 band matrices for SH of degree 3"):
        rotate_sh_bands(coeffs, bands[:2])


def test_numpy_in_numpy_out_writable_and_degree_zero_broadcasts():
    """NumPy coefficients and rotations give a writable NumPy array (callers fill it in); at
    degree 0 (no band matrix) the rotations' leading dimensions still broadcast."""
    rots = Rotation.random(5, random_state=3).as_matrix()
    rotated = rotate_sh(np.ones((5, 16, 3)), rots)
    assert isinstance(rotated, np.ndarray) and rotated.flags.writeable and rotated.shape == (5, 16, 3)
    dc = rotate_sh(np.full((1, 3), 0.25), rots)
    assert dc.shape == (5, 1, 3) and dc.flags.writeable
    np.testing.assert_array_equal(dc, 0.25)


def test_degree_inference():
    assert [sh_degree_from_coeffs(k) for k in (1, 4, 9, 16)] == [0, 1, 2, 3]
    with pytest.raises(ValueError, match="not"):
        sh_degree_from_coeffs(5)
