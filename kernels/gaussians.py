"""Gaussians as a pytree, quaternion algebra, covariances and Sim(3) transforms.

Conventions: quaternions are (w, x, y, z) and need not be unit length (the 3DGS
PLY stores them unnormalized; every consumer normalizes). Scales are stored as
logs and opacities as logits, exactly as in the INRIA PLY.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from kernels.pytree import pytree_dataclass
from kernels.sh import rotate_sh_bands, sh_band_rotations, sh_degree_from_coeffs

QUAT_EPS = 1e-12  # guards the normalization of a zero quaternion


@pytree_dataclass
class Gaussians:
    """A set of N 3D Gaussians with SH colour."""

    means: jax.Array           # (N, 3) world positions
    quats: jax.Array           # (N, 4) wxyz, any non-zero length
    log_scales: jax.Array      # (N, 3) log of the per-axis standard deviations
    opacity_logits: jax.Array  # (N,)  opacity = sigmoid(logit)
    sh: jax.Array              # (N, K, 3) SH coefficients, K = (degree + 1)²

    @property
    def num(self) -> int:
        return self.means.shape[-2]

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_coeffs(self.sh.shape[-2])

    @property
    def scales(self) -> jax.Array:
        return jnp.exp(self.log_scales)

    @property
    def opacities(self) -> jax.Array:
        return jax.nn.sigmoid(self.opacity_logits)

    def covariances(self) -> jax.Array:
        """(N, 3, 3) world covariances R diag(s²) Rᵀ."""
        return covariance(self.log_scales, self.quats)


# --- quaternions ---------------------------------------------------------------------


def quat_normalize(q):
    """q (..., 4) → unit quaternions (..., 4)."""
    # The four squares summed by hand: elementwise only, so a GPU fuses it with its users.
    norm2 = q[..., 0:1] ** 2 + q[..., 1:2] ** 2 + q[..., 2:3] ** 2 + q[..., 3:4] ** 2
    return q / jnp.sqrt(jnp.maximum(norm2, QUAT_EPS))


def quat_multiply(a, b):
    """Hamilton product a ⊗ b of wxyz quaternions a (..., 4), b (..., 4) (rotate by b, then by a)."""
    aw, ax, ay, az = jnp.moveaxis(a, -1, 0)
    bw, bx, by, bz = jnp.moveaxis(b, -1, 0)
    return jnp.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_conjugate(q):
    """q (..., 4) wxyz → its conjugate (..., 4)."""
    return q * jnp.array([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


def quat_to_rotmat(q):
    """q (..., 4) wxyz (normalized here) → (..., 3, 3) rotation matrices."""
    w, x, y, z = jnp.moveaxis(quat_normalize(q), -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def rotmat_to_quat(m):
    """m (..., 3, 3) rotation → (..., 4) unit wxyz with w ≥ 0.

    Shepperd's method: of the four algebraically equal formulas, use the one with
    the largest pivot, so the result is accurate for every rotation (180° included).
    """
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    pivots = jnp.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22],
        axis=-1,
    )  # 4w², 4x², 4y², 4z²
    choice = jnp.argmax(pivots, axis=-1)
    r = 0.5 * jnp.sqrt(jnp.maximum(jnp.max(pivots, axis=-1), QUAT_EPS))  # the pivot component
    f = 0.25 / r
    candidates = jnp.stack(
        [
            jnp.stack([r, (m21 - m12) * f, (m02 - m20) * f, (m10 - m01) * f], -1),
            jnp.stack([(m21 - m12) * f, r, (m01 + m10) * f, (m02 + m20) * f], -1),
            jnp.stack([(m02 - m20) * f, (m01 + m10) * f, r, (m12 + m21) * f], -1),
            jnp.stack([(m10 - m01) * f, (m02 + m20) * f, (m12 + m21) * f, r], -1),
        ],
        axis=-2,
    )
    q = jnp.take_along_axis(candidates, choice[..., None, None], axis=-2)[..., 0, :]
    return jnp.where(q[..., :1] < 0, -q, q)


def covariance(log_scales, quats):
    """log_scales (..., 3), quats (..., 4) → (..., 3, 3) covariances R diag(s²) Rᵀ."""
    rot = quat_to_rotmat(quats)
    m = rot * jnp.exp(log_scales)[..., None, :]  # R S
    return m @ jnp.swapaxes(m, -1, -2)


# --- Sim(3) --------------------------------------------------------------------------


@pytree_dataclass
class Sim3:
    """x ↦ s R x + t.  Batched by leading dimensions (vmap or broadcasting)."""

    quat: jax.Array         # (..., 4) wxyz rotation
    translation: jax.Array  # (..., 3)
    scale: jax.Array        # (...,)  positive

    @staticmethod
    def identity(dtype: jnp.dtype = jnp.float32) -> "Sim3":
        return Sim3(jnp.array([1.0, 0, 0, 0], dtype), jnp.zeros(3, dtype), jnp.ones((), dtype))

    @staticmethod
    def from_matrix(matrix) -> "Sim3":
        """matrix (..., 4, 4) similarity (s R | t) → Sim3; s = cbrt(det of the 3×3 block)."""
        block = matrix[..., :3, :3]
        scale = jnp.cbrt(jnp.linalg.det(block))
        rot = block / scale[..., None, None]
        return Sim3(rotmat_to_quat(rot), matrix[..., :3, 3], scale)

    @property
    def rotation(self):
        """(..., 3, 3)."""
        return quat_to_rotmat(self.quat)

    def as_matrix(self):
        """(..., 4, 4) homogeneous matrix."""
        top = jnp.concatenate(
            [self.scale[..., None, None] * self.rotation, self.translation[..., :, None]], axis=-1
        )
        bottom = jnp.broadcast_to(
            jnp.array([0, 0, 0, 1], dtype=top.dtype), top.shape[:-2] + (1, 4)
        )
        return jnp.concatenate([top, bottom], axis=-2)

    def apply(self, points):
        """points (..., P, 3) → (..., P, 3)."""
        return self.scale[..., None, None] * points @ jnp.swapaxes(
            self.rotation, -1, -2
        ) + self.translation[..., None, :]

    def compose(self, other: "Sim3") -> "Sim3":
        """self ∘ other: apply ``other`` first."""
        quat = quat_normalize(quat_multiply(self.quat, other.quat))
        translation = (
            self.scale[..., None] * jnp.einsum("...ij,...j->...i", self.rotation, other.translation)
            + self.translation
        )
        return Sim3(quat, translation, self.scale * other.scale)

    def inverse(self) -> "Sim3":
        inv_scale = 1.0 / self.scale
        quat = quat_conjugate(quat_normalize(self.quat))
        translation = -inv_scale[..., None] * jnp.einsum(
            "...ji,...j->...i", self.rotation, self.translation
        )
        return Sim3(quat, translation, inv_scale)


def transform_gaussians(gaussians: Gaussians, transform: Sim3) -> Gaussians:
    """The Gaussian set moved by a similarity: μ' = sRμ + t, Σ' = s² R Σ Rᵀ.

    ``transform`` is one Sim3 for the whole set, or one per Gaussian (leaves with a
    leading (N,) axis).
    Σ' is expressed exactly in the stored parameters (q' = q_R ⊗ q, log s' = log s + log s_T),
    and the SH coefficients of degree 1–3 are rotated so view-dependent colour turns
    with the object.
    """
    return _moved(gaussians, transform, None)


def transform_bodies(gaussians: Gaussians, transforms: Sim3, body) -> Gaussians:
    """Each Gaussian moved by the transform of its body (``transform_gaussians``).

    transforms: Sim3 with (K,) leaves (one per body); body: (N,) int body index per Gaussian.
    Each body's rotation and SH band matrices are built once and gathered per Gaussian.
    """
    return _moved(gaussians, transforms, body)


def _moved(gaussians: Gaussians, transform: Sim3, body) -> Gaussians:
    """``transform_gaussians`` with each Gaussian's transform gathered from ``transform``'s
    leaves by body (N,) int32, or the transform as it is (body None)."""
    rot_quat = quat_normalize(transform.quat)
    rot = quat_to_rotmat(rot_quat)
    parts = (rot_quat, rot, jnp.asarray(transform.scale), transform.translation,
             sh_band_rotations(rot, sh_degree_from_coeffs(gaussians.sh.shape[-2])))
    if body is not None:
        parts = jax.tree.map(lambda leaf: leaf[body], parts)
    rot_quat, rot, scale, translation, bands = parts
    # R μ as three broadcast products (elementwise: fused, no batched matrix product)
    rotated = sum(rot[..., :, k] * gaussians.means[..., k:k + 1] for k in range(3))
    means = scale[..., None] * rotated + translation
    sh = rotate_sh_bands(gaussians.sh, bands)
    # degree 0 has no band matrix: the transform's leading dimensions still reach the colours
    return Gaussians(
        means=means,
        quats=quat_multiply(rot_quat, gaussians.quats),
        log_scales=gaussians.log_scales + jnp.log(scale)[..., None],
        opacity_logits=gaussians.opacity_logits,
        sh=jnp.broadcast_to(sh, means.shape[:-1] + sh.shape[-2:]),
    )


def concatenate(parts: list[Gaussians]) -> Gaussians:
    """One set holding every Gaussian of ``parts`` (same SH degree), in order: NumPy arrays when
    every part's are (joined on the host, no program), else JAX arrays."""
    def join(*leaves):
        xp = np if all(isinstance(leaf, np.ndarray) for leaf in leaves) else jnp
        return xp.concatenate(leaves, axis=0)

    return jax.tree.map(join, *parts)
