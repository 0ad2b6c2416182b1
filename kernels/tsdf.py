"""Truncated signed distance fusion of depth images on a sparse grid of voxel blocks.

The kernel is written for one frame (``frame_tsdf``: voxel centres, one depth image →
each voxel's truncated SDF and weight) and batched with ``vmap`` over the frames of a
step; ``fuse`` scans over steps and keeps running sums, so the result is the weighted
mean Σ wₖ tsdfₖ / Σ wₖ over frames — order-independent, the same average Open3D's
running update computes.

Conventions (Open3D's ``UniformTSDFVolume``, so the two can be compared value for value):
the SDF is projective, sdf = (depth(pixel) − z_camera(voxel centre)) · ‖ray through the
pixel centre (z = 1)‖, i.e. measured along the ray; a voxel is updated only where
depth > 0 and sdf > −truncation (farther behind the surface is unknown); the
stored value is min(1, sdf / truncation) ∈ [−1, 1] and each observation weighs 1. The
pixel of a voxel is the one containing its projection: pixel centres at (i + 0.5, j + 0.5),
so pixel i covers [i, i + 1) (docs/architecture.md "Contracts").

Shapes: blocks are cubes of ``res`` voxels per edge, origin = their minimum corner;
voxel (b, x, y, z) has centre origin_b + (x + ½, y + ½, z + ½)·voxel, flattened in that
order. Block counts are padded by the caller (``block_valid`` masks the padding) so a
second scene in the same bucket does not recompile.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp


def voxel_centres(block_origins, voxel: float, res: int):
    """block_origins (B, 3) block minimum corners → (B·res³, 3) voxel centres, block-major, then x, y, z."""
    idx = jnp.arange(res, dtype=block_origins.dtype)
    grid = jnp.stack(jnp.meshgrid(idx, idx, idx, indexing="ij"), axis=-1).reshape(-1, 3)  # (res³, 3)
    return (block_origins[:, None, :] + (grid[None] + 0.5) * voxel).reshape(-1, 3)


def frame_tsdf(centres, depth, K, world_to_camera, truncation):
    """One frame's observation of every voxel.

    centres (V, 3) world; depth (H, W) metres, 0 = no measurement; K (3, 3);
    world_to_camera (4, 4); truncation () metres. Returns tsdf (V,) in [−1, 1] (0 where unobserved) and
    weight (V,) ∈ {0, 1}.
    """
    height, width = depth.shape
    cam = centres @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    z = cam[:, 2]
    safe_z = jnp.where(z > 0, z, 1.0)
    u = K[0, 0] * cam[:, 0] / safe_z + K[0, 1] * cam[:, 1] / safe_z + K[0, 2]
    v = K[1, 1] * cam[:, 1] / safe_z + K[1, 2]
    # floor of a float far outside the image can overflow int32: clamp first
    col = jnp.floor(jnp.clip(u, -1.0, width)).astype(jnp.int32)
    row = jnp.floor(jnp.clip(v, -1.0, height)).astype(jnp.int32)
    inside = (z > 0) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
    d = depth[jnp.clip(row, 0, height - 1), jnp.clip(col, 0, width - 1)]
    # distance along the pixel's ray, not along z: (d − z) · |ray through the pixel centre|
    x_n = (col + 0.5 - K[0, 2]) / K[0, 0]
    y_n = (row + 0.5 - K[1, 2]) / K[1, 1]
    sdf = (d - z) * jnp.sqrt(1.0 + x_n * x_n + y_n * y_n)
    observed = inside & (d > 0) & (sdf > -truncation)
    tsdf = jnp.where(observed, jnp.minimum(1.0, sdf / truncation), 0.0)
    return tsdf, observed.astype(centres.dtype)


@partial(jax.jit, static_argnames=("voxel", "res", "frames_per_step"))
def fuse(block_origins, block_valid, depths, Ks, world_to_cameras, truncation, *,
         voxel: float, res: int, frames_per_step: int):
    """Fuse F depth frames into B blocks.

    block_origins (B, 3); block_valid (B,) bool (padding blocks stay empty);
    depths (F, H, W) with F a multiple of ``frames_per_step`` (pad with all-zero frames);
    Ks (F, 3, 3); world_to_cameras (F, 4, 4); truncation () metres. Returns tsdf (B, res, res, res) — the mean
    of the observations, 0 where none — and weight (B, res, res, res), the count.
    """
    centres = voxel_centres(block_origins, voxel, res)
    per_step = jax.vmap(frame_tsdf, in_axes=(None, 0, 0, 0, None))
    num_steps = depths.shape[0] // frames_per_step

    def chunks(x):
        return x.reshape((num_steps, frames_per_step) + x.shape[1:])

    def step(carry, frames):
        total, count = carry
        tsdf, weight = per_step(centres, *frames, truncation)
        return (total + jnp.sum(tsdf * weight, axis=0), count + jnp.sum(weight, axis=0)), None

    zeros = jnp.zeros(centres.shape[0], centres.dtype)
    (total, count), _ = jax.lax.scan(step, (zeros, zeros), (chunks(depths), chunks(Ks), chunks(world_to_cameras)))
    valid = jnp.repeat(block_valid, res**3)
    count = jnp.where(valid, count, 0.0)
    tsdf = jnp.where(count > 0, total / jnp.maximum(count, 1.0), 0.0)
    shape = (block_origins.shape[0], res, res, res)
    return tsdf.reshape(shape), count.reshape(shape)
