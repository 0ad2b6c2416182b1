"""TSDF fusion kernel against a per-voxel NumPy loop and Open3D's UniformTSDFVolume,
plus its properties: frame order and padding do not matter, one program per bucket."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from kernels.tsdf import frame_tsdf, fuse, voxel_centres

VALUE_TOL = 1e-5            # float32 kernel vs float64 loop
OPEN3D_VALUE_TOL = 1e-4     # float32 vs float32, different operation order
OPEN3D_AGREE = 0.995        # fraction of voxels within OPEN3D_VALUE_TOL (pixel ties at u = i exactly)
OPEN3D_MAX_DIFF = 0.05      # the rest: a neighbouring pixel's depth, never more than this
TRUNC = 0.03


def look_at(eye, target, up=(0.0, 0.0, 1.0)):
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    rot = np.stack([right, np.cross(forward, right), forward])
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, -rot @ eye
    return out


def sphere_frames(centre, radius, n=8, width=40, height=30, focal=50.0):
    """Analytic depth renders of a sphere from a ring of cameras: depths, Ks, world-to-cameras."""
    K = np.array([[focal, 0, width / 2 + 0.3], [0, focal, height / 2 - 0.2], [0, 0, 1.0]])
    depths, poses = [], []
    for i in range(n):
        angle = 2 * np.pi * i / n
        eye = np.array([0.5 * np.cos(angle), 0.5 * np.sin(angle), 0.25 * (-1) ** i])
        w2c = look_at(eye, np.zeros(3))
        jj, ii = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
        rays = np.stack([ii + 0.5, jj + 0.5, np.ones_like(ii, float)], -1) @ np.linalg.inv(K).T @ w2c[:3, :3]
        oc = eye - centre
        a, b, c = (rays**2).sum(-1), 2 * rays @ oc, oc @ oc - radius**2
        disc = b * b - 4 * a * c
        depths.append(np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), 0.0))
        poses.append(w2c)
    return np.stack(depths), np.tile(K, (n, 1, 1)), np.stack(poses)


def reference_fuse(centres, depths, Ks, poses, trunc):
    """Slow and obvious: every voxel, every frame, Open3D's rules, float64."""
    total, count = np.zeros(len(centres)), np.zeros(len(centres))
    for depth, K, pose in zip(depths, Ks, poses):
        h, w = depth.shape
        for v, p in enumerate(centres):
            x, y, z = pose[:3, :3] @ p + pose[:3, 3]
            if z <= 0:
                continue
            u, w_ = K[0, 0] * x / z + K[0, 2], K[1, 1] * y / z + K[1, 2]
            col, row = int(np.floor(u)), int(np.floor(w_))
            if not (0 <= col < w and 0 <= row < h) or depth[row, col] <= 0:
                continue
            ray = np.sqrt(1 + ((col + 0.5 - K[0, 2]) / K[0, 0]) ** 2 + ((row + 0.5 - K[1, 2]) / K[1, 1]) ** 2)
            sdf = (depth[row, col] - z) * ray
            if sdf > -trunc:
                total[v] += min(1.0, sdf / trunc)
                count[v] += 1
    return np.where(count > 0, total / np.maximum(count, 1), 0.0), count


def run_fuse(origins, depths, Ks, poses, voxel, res, step=4, valid=None):
    valid = np.ones(len(origins), bool) if valid is None else valid
    tsdf, weight = fuse(jnp.asarray(origins, jnp.float32), jnp.asarray(valid), jnp.asarray(depths, jnp.float32),
                        jnp.asarray(Ks, jnp.float32), jnp.asarray(poses, jnp.float32), jnp.float32(TRUNC),
                        voxel=voxel, res=res, frames_per_step=step)
    return np.asarray(tsdf), np.asarray(weight)


def test_fuse_matches_numpy_loop():
    depths, Ks, poses = sphere_frames(np.array([0.01, 0.0, -0.01]), 0.08, n=4)
    origins = np.array([[-0.1, -0.1, -0.1], [0.0, -0.1, 0.0], [0.05, 0.05, -0.05]])
    voxel, res = 0.025, 4
    tsdf, weight = run_fuse(origins, depths, Ks, poses, voxel, res)
    centres = np.asarray(voxel_centres(jnp.asarray(origins, jnp.float32), voxel, res))
    ref_tsdf, ref_weight = reference_fuse(centres, depths, Ks, poses, TRUNC)
    assert ref_weight.sum() > 20 and (ref_weight == 0).sum() > 20  # both cases are exercised
    np.testing.assert_array_equal(weight.ravel(), ref_weight)
    np.testing.assert_allclose(tsdf.ravel(), ref_tsdf, atol=VALUE_TOL)


def test_frame_tsdf_single_frame_matches_loop():
    rng = np.random.default_rng(3)
    depth = rng.uniform(0.3, 0.6, size=(7, 9))
    depth[2, 3] = 0.0  # a hole: no measurement
    K = np.array([[8.0, 0.0, 4.4], [0.0, 8.5, 3.6], [0, 0, 1]])
    pose = look_at(np.array([0.0, -0.5, 0.1]), np.zeros(3))
    centres = rng.uniform(-0.2, 0.2, size=(300, 3))
    tsdf, weight = frame_tsdf(jnp.asarray(centres, jnp.float32), jnp.asarray(depth, jnp.float32),
                              jnp.asarray(K, jnp.float32), jnp.asarray(pose, jnp.float32), TRUNC)
    ref_tsdf, ref_weight = reference_fuse(centres, depth[None], K[None], pose[None], TRUNC)
    assert 0 < ref_weight.sum() < len(centres)
    np.testing.assert_array_equal(np.asarray(weight), ref_weight)
    np.testing.assert_allclose(np.asarray(tsdf), ref_tsdf, atol=VALUE_TOL)


def test_fuse_matches_open3d_uniform_volume():
    o3d = pytest.importorskip("open3d")
    depths, Ks, poses = sphere_frames(np.zeros(3), 0.1, n=8, width=64, height=48, focal=80.0)
    res, length = 16, 0.32
    origin = np.full(3, -length / 2)
    volume = o3d.pipelines.integration.UniformTSDFVolume(
        length=length, resolution=res, sdf_trunc=TRUNC,
        color_type=o3d.pipelines.integration.TSDFVolumeColorType.NoColor, origin=origin)
    K = Ks[0]
    intrinsic = o3d.camera.PinholeCameraIntrinsic(64, 48, K[0, 0], K[1, 1], K[0, 2] - 0.5, K[1, 2] - 0.5)
    for depth, pose in zip(depths, poses):
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.zeros((48, 64, 3), np.uint8)), o3d.geometry.Image(depth.astype(np.float32)),
            depth_scale=1.0, depth_trunc=10.0, convert_rgb_to_intensity=False)
        volume.integrate(rgbd, intrinsic, pose)
    expected = np.asarray(volume.extract_volume_tsdf())  # (res³, 2) tsdf, weight; x-major like ours
    tsdf, weight = run_fuse(origin[None], depths, Ks, poses, length / res, res)
    observed = expected[:, 1] > 0
    assert 0.2 < observed.mean() < 0.9
    np.testing.assert_array_equal(weight.ravel(), expected[:, 1])
    diff = np.abs(tsdf.ravel() - expected[:, 0])[observed]
    assert np.mean(diff < OPEN3D_VALUE_TOL) >= OPEN3D_AGREE and diff.max() < OPEN3D_MAX_DIFF


def test_frame_order_padding_frames_and_padding_blocks_do_not_matter():
    depths, Ks, poses = sphere_frames(np.zeros(3), 0.09, n=6)
    origins = np.array([[-0.1, -0.1, -0.1], [-0.1, 0.0, 0.0]])
    voxel, res = 0.0125, 8
    tsdf, weight = run_fuse(origins, depths, Ks, poses, voxel, res, step=2)
    perm = np.random.default_rng(0).permutation(6)
    t2, w2 = run_fuse(origins, depths[perm], Ks[perm], poses[perm], voxel, res, step=2)
    np.testing.assert_allclose(t2, tsdf, atol=1e-6)
    np.testing.assert_array_equal(w2, weight)
    # two all-zero frames and two padding blocks (placed where the sphere is) change nothing
    pad_d = np.concatenate([depths, np.zeros((2,) + depths.shape[1:])])
    pad_K, pad_p = np.concatenate([Ks, Ks[:2]]), np.concatenate([poses, poses[:2]])
    pad_o = np.concatenate([origins, origins])
    t3, w3 = run_fuse(pad_o, pad_d, pad_K, pad_p, voxel, res, step=4, valid=np.array([1, 1, 0, 0], bool))
    np.testing.assert_allclose(t3[:2], tsdf, atol=1e-6)
    np.testing.assert_array_equal(w3[:2], weight)
    assert np.all(w3[2:] == 0) and np.all(t3[2:] == 0)


def test_same_bucket_compiles_once():
    depths, Ks, poses = sphere_frames(np.zeros(3), 0.09, n=4)
    before = fuse._cache_size()
    for shift in (0.0, 0.013, -0.021):  # different scenes, same shapes
        run_fuse(np.full((4, 3), -0.1) + shift, depths, Ks, poses, 0.01, 4)
    assert fuse._cache_size() == before + 1
