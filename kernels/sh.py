"""Real spherical harmonics in the 3DGS convention, degree 0–3, and their exact rotation.

Band ordering, signs and constants follow the INRIA 3DGS implementation, so a PLY
trained by any 3DGS tool looks the same here: colour = clamp(Σ_k c_k Y_k(d) + 0.5, 0),
with d the unit direction from the camera centre to the Gaussian.

Coefficients are laid out (..., K, 3) with K = (degree + 1)², band-major.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
         -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)
MAX_SH_DEGREE = 3


def num_sh_coeffs(degree: int) -> int:
    return (degree + 1) ** 2


def sh_degree_from_coeffs(num_coeffs: int) -> int:
    """Inverse of ``num_sh_coeffs``; raises for a count that is not (d + 1)², d ≤ 3."""
    for degree in range(MAX_SH_DEGREE + 1):
        if num_sh_coeffs(degree) == num_coeffs:
            return degree
    raise ValueError(f"{num_coeffs} SH coefficients per channel is not (d + 1)² for d in 0..3")


def sh_basis(dirs, degree: int):
    """Basis values Y_k(d).  dirs: (..., 3) unit vectors → (..., (degree + 1)²).

    NumPy in → NumPy out (float64 tables at import time); JAX in → JAX out.
    """
    xp = np if isinstance(dirs, np.ndarray) else jnp
    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    one = xp.ones_like(x)
    out = [SH_C0 * one]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2.0 * zz - xx - yy),
            SH_C2[3] * x * z,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3.0 * xx - yy),
            SH_C3[1] * x * y * z,
            SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3.0 * yy),
        ]
    return xp.stack(out, axis=-1)


def eval_sh(coeffs, dirs):
    """Σ_k c_k Y_k(d) without the +0.5 offset.  coeffs: (..., K, 3), dirs: (..., 3) unit → (..., 3)."""
    degree = sh_degree_from_coeffs(coeffs.shape[-2])
    basis = sh_basis(dirs, degree)
    return jnp.einsum("...k,...kc->...c", basis, coeffs)


def sh_to_rgb(coeffs, dirs):
    """3DGS colour: clamp(eval_sh + 0.5, min=0).  coeffs (..., K, 3), dirs (..., 3) unit → (..., 3)."""
    return jnp.maximum(eval_sh(coeffs, dirs) + 0.5, 0.0)


def rgb_to_sh_dc(rgb):
    """DC coefficient that reproduces ``rgb`` (..., 3) in every direction."""
    return (rgb - 0.5) / SH_C0


# --- rotation ---------------------------------------------------------------------
#
# Band l spans a rotation-invariant space, so y_l(Rᵀd) = y_l(d) W_l(R) for a
# (2l+1)² matrix W_l. Sampling 2l+1 fixed, well-spread directions D gives
# W_l = Y_l(D)⁻¹ Y_l(D R): exact (no fitting), convention-agnostic (it uses the
# very basis above), and only an evaluation of the basis at rotated directions.


def _sample_directions(band: int, seed: int = 7, tries: int = 256) -> np.ndarray:
    """(2l+1, 3) unit directions whose band-l basis matrix is best conditioned."""
    rng = np.random.default_rng(seed + band)
    size = 2 * band + 1
    lo, hi = band * band, (band + 1) ** 2
    best, best_cond = None, np.inf
    for _ in range(tries):
        d = rng.normal(size=(size, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        cond = np.linalg.cond(sh_basis(d, band)[:, lo:hi])
        if cond < best_cond:
            best, best_cond = d, cond
    return best


def _build_rotation_tables():
    dirs, inverses = [], []
    for band in range(1, MAX_SH_DEGREE + 1):
        d = _sample_directions(band)
        lo, hi = band * band, (band + 1) ** 2
        dirs.append(d)
        inverses.append(np.linalg.inv(sh_basis(d, band)[:, lo:hi]))
    return tuple(dirs), tuple(inverses)


_ROT_DIRS, _ROT_INVERSES = _build_rotation_tables()


def sh_band_rotation(rotation, band: int):
    """(..., 2l+1, 2l+1) matrices W with c'_l = W c_l, for rotation (..., 3, 3) (NumPy or JAX)."""
    xp = np if isinstance(rotation, np.ndarray) else jnp
    lo, hi = band * band, (band + 1) ** 2
    dirs = xp.asarray(_ROT_DIRS[band - 1], dtype=rotation.dtype)
    inv = xp.asarray(_ROT_INVERSES[band - 1], dtype=rotation.dtype)
    rotated = sh_basis(dirs @ rotation, band)[..., lo:hi]  # rows y_l(Rᵀ d_k)
    return inv @ rotated


def sh_band_rotations(rotation, degree: int) -> tuple:
    """(W₁, …, W_degree): each band's (..., 2l+1, 2l+1) matrix for rotation (..., 3, 3)
    (``sh_band_rotation``; NumPy or JAX). Built once per rotation, they rotate any number of
    coefficient sets (``rotate_sh_bands``)."""
    return tuple(sh_band_rotation(rotation, band) for band in range(1, degree + 1))


def rotate_sh_bands(coeffs, bands: tuple):
    """coeffs (..., K, 3) rotated by the band matrices ``bands`` (``sh_band_rotations``, one per
    band of degree 1 and up, leading dimensions broadcasting against those of coeffs).

    bands: (W₁ (..., 3, 3), …, W_d (..., 2d+1, 2d+1)) for degree d.

    In JAX, c'_l = W_l c_l is written as 2l+1 broadcast products and a sum: under vmap only
    elementwise operations, which a GPU fuses into their consumer (a batch of tiny matrix
    products would be a matrix-multiply kernel of its own for each band). NumPy, which fuses
    nothing, takes the matrix products."""
    xp = np if isinstance(coeffs, np.ndarray) and all(isinstance(w, np.ndarray) for w in bands) else jnp
    degree = sh_degree_from_coeffs(coeffs.shape[-2])
    if len(bands) != degree:
        raise ValueError(f"rotate_sh_bands: {len(bands)} band matrices for SH of degree {degree}")
    lead = np.broadcast_shapes(coeffs.shape[:-2], *(w.shape[:-2] for w in bands))
    out = [xp.broadcast_to(coeffs[..., :1, :], lead + (1, 3))]
    for band, w in enumerate(bands, start=1):
        lo, hi = band * band, (band + 1) ** 2
        w = w.astype(coeffs.dtype)
        if xp is np:
            out.append(np.broadcast_to(np.einsum("...ij,...jc->...ic", w, coeffs[..., lo:hi, :]),
                                       lead + (hi - lo, 3)))
        else:
            out.append(jnp.sum(w[..., :, :, None] * coeffs[..., None, lo:hi, :], axis=-2))
    return xp.concatenate(out, axis=-2)


def rotate_sh(coeffs, rotation):
    """Coefficients of the same radiance field rotated by ``rotation``.

    coeffs: (..., K, 3); rotation: (3, 3) or (..., 3, 3) proper rotations broadcasting
    against the leading dimensions of ``coeffs``. NumPy in → NumPy out. The result
    satisfies eval_sh(rotate_sh(c, R), d) = eval_sh(c, Rᵀ d): the colour seen along d
    after an object rotates by R is the colour it showed along Rᵀ d before.
    """
    rotated = rotate_sh_bands(coeffs, sh_band_rotations(rotation, sh_degree_from_coeffs(coeffs.shape[-2])))
    # degree 0 has no band matrix: the rotations' leading dimensions still broadcast
    lead = np.broadcast_shapes(rotated.shape[:-2], rotation.shape[:-2])
    if lead == rotated.shape[:-2]:
        return rotated
    if isinstance(rotated, np.ndarray) and isinstance(rotation, np.ndarray):
        return np.broadcast_to(rotated, lead + rotated.shape[-2:]).copy()  # writable, as NumPy's results are
    return jnp.broadcast_to(rotated, lead + rotated.shape[-2:])
