"""EWA projection of 3D Gaussians into one pinhole camera (the 3DGS front end).

For one Gaussian (then vmapped): camera-space mean, the Jacobian of the perspective
projection at that mean, the screen-space covariance J W Σ Wᵀ Jᵀ + 0.3·I, its inverse
(the "conic"), the 3σ screen radius, the tile rectangle it touches, and its colour from
SH evaluated along the unit direction camera centre → mean.

Conventions (docs/architecture.md "Contracts"): OpenCV camera axes, ``world_to_camera`` 4×4,
pinhole ``K`` (skew allowed), pixel centres at (i + 0.5, j + 0.5) in K's coordinates.
A tile t = (tx, ty) of size T covers the pixel centres in [T·tx, T·tx + T) × [T·ty, T·ty + T);
a Gaussian touches every tile that the bounding box of its ellipse at k σ overlaps, half-widths
k √Σxx and k √Σyy, with k = min(3, √(2 ln(o / α_min))): beyond that ellipse its α is below
α_min (skipped) or it is past 3σ. (A square of side 2 · 3σ_major, as 3DGS bins, holds more
tiles for an elongated or faint Gaussian, and those extra tiles receive nothing above α_min
but the 3σ cut's corners.)
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from kernels.gaussians import Gaussians, quat_to_rotmat
from kernels.pytree import pytree_dataclass
from kernels.sh import sh_basis, sh_degree_from_coeffs

SCREEN_DILATION = 0.3  # px², added to the 2D covariance: the 3DGS low-pass / anti-alias filter
SIGMA_EXTENT = 3.0     # screen radius = 3σ along the major axis
NEAR_PLANE = 0.01      # m; Gaussians whose mean has view depth ≤ this are culled
ALPHA_MIN = 1.0 / 255.0  # α below this is skipped; so is a Gaussian whose opacity is below it
# The Jacobian is evaluated at the mean clamped to the image plus this fraction of the
# half image on each side (3DGS's 1.3 × tan(fov/2)): far off-screen means would
# otherwise give huge, meaningless affine approximations.
JACOBIAN_MARGIN = 0.3
DIR_EPS = 1e-12        # guards the normalization of a zero view direction


@pytree_dataclass
class Projected:
    """Per-Gaussian screen-space quantities for one camera."""

    means2d: jax.Array    # (N, 2) pixel coordinates in K's frame
    conics: jax.Array     # (N, 3) upper triangle (a, b, c) of the inverse 2D covariance
    depths: jax.Array     # (N,) view-space z of the mean (metres)
    opacities: jax.Array  # (N,) sigmoid(opacity_logit)
    colors: jax.Array     # (N, 3) clamp(SH(dir) + 0.5, 0)
    radii: jax.Array      # (N,) 3σ radius in pixels, 0 where culled (no gradient)
    rects: jax.Array      # (N, 4) int32 inclusive tile rectangle (x0, y0, x1, y1); empty if x1 < x0
    visible: jax.Array    # (N,) bool: in front of the near plane, opaque enough, touches a tile


def _mm(a, b):
    """a (M, K) · b (K, L) written out as K broadcast products: under vmap, only elementwise
    operations, which a GPU fuses into the projection's one kernel (a batched 3×3 matrix
    product or a length-3 reduction would each be a kernel of its own)."""
    out = a[:, 0:1] * b[0:1, :]
    for k in range(1, a.shape[1]):
        out = out + a[:, k:k + 1] * b[k:k + 1, :]
    return out


def camera_center(world_to_camera):
    """world_to_camera (4, 4) → (3,) camera centre in world coordinates: −Rᵀt."""
    rot, trans = world_to_camera[:3, :3], world_to_camera[:3, 3]
    return -rot.T @ trans


def _project_one(mean, quat, log_scale, opacity_logit, sh, K, world_to_camera, center,
                 width: int, height: int, tiles_x: int, tiles_y: int, tile_size: int, near: float):
    """One Gaussian → the fields of ``Projected`` (scalars / small vectors).

    mean (3,); quat (4,) wxyz; log_scale (3,); opacity_logit (); sh (K, 3); K (3, 3);
    world_to_camera (4, 4); center (3,) camera centre (``camera_center``).
    """
    rot, trans = world_to_camera[:3, :3], world_to_camera[:3, 3]
    p = _mm(rot, mean[:, None])[:, 0] + trans  # (3,) camera-space mean
    z = p[2]
    in_front = z > near
    zs = jnp.where(in_front, z, 1.0)  # safe depth: culled Gaussians stay finite (and NaN-free in grads)

    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    margin_x = 0.5 * JACOBIAN_MARGIN * width / fx
    margin_y = 0.5 * JACOBIAN_MARGIN * height / fy
    xz = jnp.clip(p[0] / zs, -cx / fx - margin_x, (width - cx) / fx + margin_x)
    yz = jnp.clip(p[1] / zs, -cy / fy - margin_y, (height - cy) / fy + margin_y)
    # d(x/z, y/z)/d(x, y, z) at the clamped point, then through K's 2×2 block.
    jac_n = jnp.stack([
        jnp.stack([1.0 / zs, jnp.zeros_like(zs), -xz / zs]),
        jnp.stack([jnp.zeros_like(zs), 1.0 / zs, -yz / zs]),
    ])
    jac = _mm(K[:2, :2], jac_n)  # (2, 3)
    m = _mm(jac, rot)            # (2, 3): world → screen linear map
    # Σ₂ = M R S (M R S)ᵀ with the Gaussian's rotation R and scales S: a 2×3 factor.
    factor = _mm(m, quat_to_rotmat(quat)) * jnp.exp(log_scale)[None, :]
    cov2d = _mm(factor, factor.T) + SCREEN_DILATION * jnp.eye(2, dtype=mean.dtype)

    uv = _mm(K[:2, :2], (p[:2] / zs)[:, None])[:, 0] + K[:2, 2]  # (2,)
    a, b, c = cov2d[0, 0], cov2d[0, 1], cov2d[1, 1]
    det = a * c - b * b  # ≥ 0.09 thanks to the dilation
    conic = jnp.stack([c, -b, a]) / det

    # Bookkeeping below is not differentiated (tile assignment is discrete).
    a_, c_, det_ = jax.lax.stop_gradient((a, c, det))
    mid = 0.5 * (a_ + c_)
    lam_max = mid + jnp.sqrt(jnp.maximum(mid * mid - det_, 0.0))
    radius = SIGMA_EXTENT * jnp.sqrt(lam_max)
    uv_ = jax.lax.stop_gradient(uv)

    opacity = jax.nn.sigmoid(opacity_logit)
    opacity_ = jax.lax.stop_gradient(opacity)
    alive = in_front & (opacity_ >= ALPHA_MIN) & jnp.isfinite(radius)
    # The tiles: the bounding box of the ellipse m ≤ k (m: Mahalanobis distance), half-widths
    # k √Σxx and k √Σyy. Past m² = 2 ln(o / ALPHA_MIN) the compositor skips every pixel
    # (o e^(−m²/2) < ALPHA_MIN), so k is that or SIGMA_EXTENT, the smaller.
    k = jnp.minimum(SIGMA_EXTENT, jnp.sqrt(2.0 * jnp.log(jnp.maximum(opacity_ / ALPHA_MIN, 1.0))))

    def tile_range(centre, half, n_tiles):
        # Clip before the int cast so far-away means cannot overflow int32.
        lo = jnp.floor(jnp.clip((centre - half) / tile_size, -1.0, n_tiles))
        hi = jnp.floor(jnp.clip((centre + half) / tile_size, -1.0, n_tiles))
        return jnp.maximum(lo, 0).astype(jnp.int32), jnp.minimum(hi, n_tiles - 1).astype(jnp.int32)

    x0, x1 = tile_range(uv_[0], k * jnp.sqrt(a_), tiles_x)
    y0, y1 = tile_range(uv_[1], k * jnp.sqrt(c_), tiles_y)
    touches = (x1 >= x0) & (y1 >= y0)
    visible = alive & touches
    rect = jnp.where(visible, jnp.stack([x0, y0, x1, y1]), jnp.array([0, 0, -1, -1], jnp.int32))

    direction = mean - center
    norm2 = direction[0] ** 2 + direction[1] ** 2 + direction[2] ** 2
    direction = direction / jnp.sqrt(jnp.maximum(norm2, DIR_EPS))
    basis = sh_basis(direction, sh_degree_from_coeffs(sh.shape[0]))  # (K,)
    color = jnp.maximum(_mm(basis[None, :], sh)[0] + 0.5, 0.0)  # 3DGS: clamp(SH + ½, 0)
    return uv, conic, z, opacity, color, jnp.where(visible, radius, 0.0), rect, visible


def project_gaussians(gaussians: Gaussians, K, world_to_camera, *, width: int, height: int,
                      tile_size: int = 16, near: float = NEAR_PLANE) -> Projected:
    """Project N Gaussians into one camera.

    K: (3, 3); world_to_camera: (4, 4); width, height, tile_size, near: static.
    Returns ``Projected`` with leading dimension N. Differentiable in every Gaussian
    parameter through means2d, conics, depths, opacities and colors.
    """
    tiles_x = -(-width // tile_size)
    tiles_y = -(-height // tile_size)
    center = camera_center(world_to_camera)

    def one(mean, quat, log_scale, opacity_logit, sh):
        return _project_one(mean, quat, log_scale, opacity_logit, sh, K, world_to_camera, center,
                            width, height, tiles_x, tiles_y, tile_size, near)

    out = jax.vmap(one)(gaussians.means, gaussians.quats, gaussians.log_scales,
                        gaussians.opacity_logits, gaussians.sh)
    return Projected(*out)
