"""TSDF fusion throughput: ``kernels.tsdf.fuse`` (JAX, any backend) vs Open3D's VoxelBlockGrid.

Two steps, so the JAX part can run on a machine with only jax + numpy (a GPU box):

    # here: render a scene's depth once, choose the blocks, save everything the kernel needs
    python -m experiments.tsdf_bench make SCENE_DIR data.npz
    # anywhere: time the kernel (compile and run separately), and Open3D when it is installed
    python -m experiments.tsdf_bench time data.npz --out result.json

Prints and writes JSON: compile seconds, run seconds (median of repeats, block_until_ready),
voxel updates per second (voxels × frames / run time).
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time
from pathlib import Path

import numpy as np

from experiments.report import emit


def make(scene_dir: Path, out: Path) -> None:
    from phirie_jax.io.scene import load_scene
    from phirie_jax.observe.config import ObserveConfig
    from phirie_jax.observe.stage import render_depths
    from phirie_jax.observe.surface import active_blocks, bucket

    config = ObserveConfig().surface
    scene = load_scene(scene_dir)
    depths, cams, _ = render_depths(scene, ObserveConfig())
    depths = [np.where((d > 0) & (d <= config.depth_max), d, 0.0).astype(np.float32) for d in depths]
    blocks = active_blocks(depths, cams, config.truncation, config.voxel, config.block)
    padded = bucket(len(blocks))
    origins = np.zeros((padded, 3), np.float32)
    origins[: len(blocks)] = blocks * (config.voxel * config.block)
    np.savez_compressed(out, depths=np.stack(depths), Ks=np.stack([c.K for c in cams]).astype(np.float32),
                        poses=np.stack([c.world_to_camera for c in cams]).astype(np.float32),
                        origins=origins, valid=np.arange(padded) < len(blocks), voxel=config.voxel,
                        truncation=config.truncation, res=config.block, frames_per_step=config.frames_per_step,
                        depth_max=config.depth_max, blocks=len(blocks), scene=str(scene_dir))
    print(f"{out}: {len(depths)} frames {depths[0].shape}, {len(blocks)} blocks (bucket {padded})")


def time_jax(data, repeats: int) -> dict:
    import jax
    import jax.numpy as jnp

    from kernels.tsdf import fuse

    step = int(data["frames_per_step"])
    depths, Ks, poses = data["depths"], data["Ks"], data["poses"]
    pad = (-len(depths)) % step
    if pad:
        depths = np.concatenate([depths, np.zeros((pad,) + depths.shape[1:], np.float32)])
        Ks, poses = np.concatenate([Ks, Ks[:pad]]), np.concatenate([poses, poses[:pad]])
    args = [jnp.asarray(x) for x in (data["origins"], data["valid"], depths, Ks, poses)]
    args.append(jnp.float32(data["truncation"]))
    static = {"voxel": float(data["voxel"]), "res": int(data["res"]), "frames_per_step": step}
    t0 = time.perf_counter()
    compiled = fuse.lower(*args, **static).compile()
    compile_s = time.perf_counter() - t0
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        runs.append(time.perf_counter() - t0)
    voxels = int(data["origins"].shape[0]) * int(data["res"]) ** 3
    run_s = statistics.median(runs)
    return {"backend": jax.default_backend(), "device": str(jax.devices()[0]), "compile_s": round(compile_s, 3),
            "run_s": round(run_s, 4), "runs_s": [round(r, 4) for r in runs], "voxels": voxels,
            "frames": len(data["depths"]),
            "voxel_updates_per_s": round(voxels * len(depths) / run_s, 1)}


def time_open3d(data, repeats: int) -> dict | None:
    try:
        import open3d as o3d
        import open3d.core as o3c
    except ImportError:
        return None
    voxel, trunc, res = float(data["voxel"]), float(data["truncation"]), int(data["res"])
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        grid = o3d.t.geometry.VoxelBlockGrid(("tsdf", "weight"), (o3c.float32, o3c.float32), ((1), (1)),
                                             voxel, res, 1 << 16, o3c.Device("CPU:0"))
        for depth, K, pose in zip(data["depths"], data["Ks"], data["poses"]):
            image = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth)))
            K = K.astype(np.float64).copy()
            K[:2, 2] -= 0.5
            K, ext = o3c.Tensor(K), o3c.Tensor(pose.astype(np.float64))
            coords = grid.compute_unique_block_coordinates(image, K, ext, 1.0, float(data["depth_max"]),
                                                           trunc_voxel_multiplier=trunc / voxel)
            grid.integrate(coords, image, K, ext, 1.0, float(data["depth_max"]), trunc_voxel_multiplier=trunc / voxel)
        runs.append(time.perf_counter() - t0)
    return {"device": "CPU:0", "run_s": round(statistics.median(runs), 4), "runs_s": [round(r, 4) for r in runs]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("make")
    m.add_argument("scene", type=Path)
    m.add_argument("out", type=Path)
    t = sub.add_parser("time")
    t.add_argument("data", type=Path)
    t.add_argument("--repeats", type=int, default=3)
    t.add_argument("--out", type=Path)
    args = parser.parse_args()
    if args.cmd == "make":
        make(args.scene, args.out)
        return
    data = dict(np.load(args.data))
    result = {"data": str(args.data), "scene": str(data["scene"]), "blocks": int(data["blocks"]),
              "machine": {"platform": platform.platform(), "processor": platform.processor()},
              "jax": time_jax(data, args.repeats), "open3d": time_open3d(data, args.repeats)}
    emit(result, args.out)


if __name__ == "__main__":
    main()
