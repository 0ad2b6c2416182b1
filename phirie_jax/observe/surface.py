"""The scene surface: the scan mesh when there is one, else fused from rendered depth.

Splat-derived surface (the paper's Scene Observation): render depth and alpha at the
training cameras (every k-th), keep pixels with alpha ≥ 0.6, fuse a TSDF at 5 mm voxels
with ~2 cm truncation, extract a mesh. Two backends give the same surface:

- ``jax``: ``kernels.tsdf.fuse`` on a sparse grid of 8³-voxel blocks chosen on the host
  (those the truncation band of some depth sample reaches; the block count is padded
  to a power of two), then naive surface nets (``surface_nets``) on the host.
- ``open3d``: Open3D's ``VoxelBlockGrid`` (tensor API) and its marching cubes, run in a
  child process (``phirie_jax.native``) so a crash in it is a ``NativeLibraryError``.

Both grids are sized from the blocks the depth samples reach (``plan_grid``); a grid over
``SurfaceConfig.memory_budget_gb`` is refused before it is allocated
(``SurfaceTooLargeError``, naming the samples' bounds, the voxel and the block count).

Then (ours, beyond the paper) each vertex is snapped along its normal onto the opaque
Gaussian centres near it (``snap_to_centres``): alpha-composited depth of overlapping
splats is biased towards the camera, the centres are not.

``experiments/observe_eval.py`` times both; the faster is ``SurfaceConfig.backend``'s
default and the one used is recorded in the manifest.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from phirie_jax.observe.config import SurfaceConfig
from phirie_jax.types import Camera

MIN_BLOCK_BUCKET = 64   # smallest padded block count (powers of two above it)
_KEY_OFFSET = 1 << 20   # voxel/block integer coordinates are packed into 21-bit fields


@dataclasses.dataclass(frozen=True)
class SurfaceMesh:
    vertices: np.ndarray  # (V, 3) float64 world
    faces: np.ndarray     # (F, 3) int64, counter-clockwise seen from outside (free space)
    info: dict            # how it was made: backend, voxel, timings, sizes

    def to_trimesh(self):
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, process=False)


def pack_keys(coords: np.ndarray) -> np.ndarray:
    """(N, 3) integer coordinates in (−2²⁰, 2²⁰) → (N,) int64 keys (one per cell, order-preserving in x)."""
    c = np.asarray(coords, np.int64) + _KEY_OFFSET
    return (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]


def unpack_keys(keys: np.ndarray) -> np.ndarray:
    mask = (1 << 21) - 1
    return np.stack([(keys >> 42) & mask, (keys >> 21) & mask, keys & mask], axis=1) - _KEY_OFFSET


def bucket(n: int, minimum: int = MIN_BLOCK_BUCKET) -> int:
    """The static size for n items: the next power of two, at least ``minimum``."""
    return max(minimum, 1 << max(0, int(np.ceil(np.log2(max(n, 1))))))


def backproject(depth: np.ndarray, camera: Camera, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """World points (P, 3) of the valid (> 0) depth pixels on a stride, and their ray directions (z_cam = 1)."""
    from phirie_jax.observe.raycast import pixel_grid, pixel_rays

    rows, cols = pixel_grid(camera.width, camera.height, stride)
    origins, dirs = pixel_rays(camera, rows, cols)
    d = depth[np.ix_(rows, cols)].ravel()
    ok = d > 0
    return origins[ok] + d[ok, None] * dirs[ok], dirs[ok]


def active_blocks(depths: list[np.ndarray], cameras: list[Camera], truncation: float, voxel: float,
                  res: int, stride: int = 2) -> np.ndarray:
    """(B, 3) integer coordinates of the blocks the truncation band of any depth sample reaches.

    Each sampled pixel marks the blocks at depth d + s·(truncation + one block diagonal step)
    for s on [−1, 1] in steps no longer than half a block, so the band is covered.
    """
    return _band_blocks(depths, cameras, truncation, voxel, res, stride)[0]


def _band_blocks(depths, cameras, truncation, voxel, res, stride):
    """``active_blocks`` and the (2, 3) min/max of the depth samples (None when there are none)."""
    block = voxel * res
    reach = truncation + voxel  # a voxel centre within the band may sit in the next block
    steps = np.linspace(-1.0, 1.0, max(3, int(np.ceil(2 * reach / (0.5 * block))) + 1))
    keys, lo, hi = [], [], []
    for depth, cam in zip(depths, cameras):
        points, dirs = backproject(depth, cam, stride)
        if len(points) == 0:
            continue
        lo.append(points.min(0))
        hi.append(points.max(0))
        unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        for s in steps:
            keys.append(np.unique(pack_keys(np.floor((points + s * reach * unit) / block))))
    if not keys:
        return np.zeros((0, 3), np.int64), None
    return unpack_keys(np.unique(np.concatenate(keys))), np.stack([np.min(lo, 0), np.max(hi, 0)])


def bytes_per_block(config: SurfaceConfig) -> int:
    """Estimated memory of one block of ``config.block``³ voxels while fusing (bytes).

    open3d: tsdf and weight (float32 each) plus the hash map's key, index and bookkeeping
    (~64 B). jax: the block's voxel centres (3 × float32), the running sum, count and outputs
    (4 × float32) and per fused frame of a step the projected voxels' depth, pixel and TSDF
    intermediates (~8 × float32).
    """
    voxels = config.block ** 3
    if config.backend == "open3d":
        return voxels * 8 + 64
    return voxels * 4 * (3 + 4 + 8 * config.frames_per_step)


def allocated_blocks(needed: int, backend: str) -> int:
    """Blocks a backend allocates for ``needed`` active ones: the JAX grid pads to a power of
    two; Open3D marks its own band per frame (it may reach a little past ours) and its hash
    map gets twice the count, also a power of two."""
    return bucket(2 * needed if backend == "open3d" else needed)


@dataclasses.dataclass(frozen=True)
class GridPlan:
    """The sparse TSDF grid a set of depth maps needs, decided before allocating it."""

    blocks: np.ndarray        # (B, 3) int64 block coordinates the truncation band reaches
    bounds: np.ndarray | None  # (2, 3) min/max of the depth samples (world units)
    bytes_needed: int          # estimate: allocated_blocks × bytes_per_block


def plan_grid(depths: list[np.ndarray], cameras: list[Camera], config: SurfaceConfig) -> GridPlan:
    """The blocks the depth reaches and their memory; raises ``SurfaceTooLargeError`` past
    ``config.memory_budget_gb`` (a one-line message with the bounds, voxel and block count)."""
    from phirie_jax.errors import SurfaceTooLargeError

    blocks, bounds = _band_blocks(depths, cameras, config.truncation, config.voxel, config.block, stride=2)
    needed = allocated_blocks(len(blocks), config.backend) * bytes_per_block(config)
    budget = config.memory_budget_gb * 1e9
    if needed > budget:
        size = bounds[1] - bounds[0]
        raise SurfaceTooLargeError(
            None, "observe.surface",
            f"the depth samples span {np.round(bounds[0], 2).tolist()} to {np.round(bounds[1], 2).tolist()} "
            f"({' × '.join(f'{v:.3g}' for v in size)} units); at voxel {config.voxel:g} the {config.backend} TSDF "
            f"needs {len(blocks):,} blocks of {config.block}³ (~{needed / 1e9:.1f} GB) > memory_budget_gb "
            f"{config.memory_budget_gb:g} (is the scene in metres? else raise voxel/truncation or the budget)")
    return GridPlan(blocks, bounds, int(needed))


def fuse_jax(depths: list[np.ndarray], cameras: list[Camera], config: SurfaceConfig, plan: GridPlan | None = None):
    """TSDF with ``kernels.tsdf``: block coords (B, 3), tsdf and weight (B, r, r, r), timings.

    The grid is ``plan``'s blocks (``plan_grid``, which refuses a grid over the memory budget)."""
    import jax.numpy as jnp

    from kernels.tsdf import fuse

    res, step = config.block, config.frames_per_step
    t0 = time.perf_counter()
    blocks = (plan or plan_grid(depths, cameras, config)).blocks
    padded = bucket(len(blocks))
    origins = np.zeros((padded, 3), np.float32)
    origins[: len(blocks)] = blocks * (config.voxel * res)
    valid = np.arange(padded) < len(blocks)
    frames = len(depths) + (-len(depths)) % step
    h, w = depths[0].shape
    depth_arr = np.zeros((frames, h, w), np.float32)
    Ks = np.tile(np.eye(3, dtype=np.float32), (frames, 1, 1))
    poses = np.tile(np.eye(4, dtype=np.float32), (frames, 1, 1))
    for i, (d, cam) in enumerate(zip(depths, cameras)):
        depth_arr[i], Ks[i], poses[i] = d, cam.K, cam.world_to_camera
    t1 = time.perf_counter()
    tsdf, weight = fuse(jnp.asarray(origins), jnp.asarray(valid), jnp.asarray(depth_arr), jnp.asarray(Ks),
                        jnp.asarray(poses), jnp.float32(config.truncation), voxel=float(config.voxel), res=res,
                        frames_per_step=step)
    tsdf, weight = np.asarray(tsdf)[: len(blocks)], np.asarray(weight)[: len(blocks)]
    t2 = time.perf_counter()
    timings = {"blocks_s": t1 - t0, "fuse_s": t2 - t1}
    return blocks, tsdf, weight, {"blocks": len(blocks), "padded_blocks": int(padded), **timings}


# The 12 edges of a cell as pairs of its 8 corners (corner c has offset ((c>>2)&1, (c>>1)&1, c&1)).
_CORNERS = np.array([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)])
_EDGES = np.array([(a, b) for a in range(8) for b in range(a + 1, 8)
                   if np.abs(_CORNERS[a] - _CORNERS[b]).sum() == 1])


def surface_nets(blocks: np.ndarray, tsdf: np.ndarray, weight: np.ndarray, voxel: float,
                 min_weight: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Zero level set of a sparse block TSDF as a triangle mesh (naive surface nets).

    blocks (B, 3) integer block coordinates; tsdf, weight (B, r, r, r) indexed (x, y, z).
    A cell (2×2×2 voxel centres, all with weight ≥ min_weight) whose corners change sign
    gets one vertex at the mean of its edges' zero crossings; each voxel edge with a sign
    change joins the four cells around it in a quad (two triangles), oriented so the
    normal points from negative (behind the surface) to positive (free space).
    Returns vertices (V, 3) world and faces (F, 3). Like any naive surface nets, a cell that
    two sheets pass through gets one vertex, so a few edges may join four faces (0.5% of the
    edges on the real RGB-D frames); Open3D's marching cubes does not have this.
    """
    res = tsdf.shape[1]
    local = np.stack(np.meshgrid(*[np.arange(res)] * 3, indexing="ij"), -1).reshape(-1, 3)
    coords = (blocks[:, None, :] * res + local[None]).reshape(-1, 3)
    keep = weight.reshape(-1) >= min_weight
    coords, values = coords[keep], tsdf.reshape(-1)[keep].astype(np.float64)
    keys = pack_keys(coords)
    order = np.argsort(keys)
    keys, coords, values = keys[order], coords[order], values[order]

    def lookup(c):
        k = pack_keys(c)
        i = np.minimum(np.searchsorted(keys, k), len(keys) - 1)
        return i, keys[i] == k if len(keys) else np.zeros(len(k), bool)

    if len(keys) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    corner_idx = np.empty((len(keys), 8), np.int64)
    corner_ok = np.empty((len(keys), 8), bool)
    for c in range(8):
        corner_idx[:, c], corner_ok[:, c] = lookup(coords + _CORNERS[c])
    vals = values[corner_idx]
    inside = vals < 0
    cell = corner_ok.all(1) & inside.any(1) & ~inside.all(1)

    # one vertex per surface cell: mean of the zero crossings on its edges
    va, vb = vals[cell][:, _EDGES[:, 0]], vals[cell][:, _EDGES[:, 1]]
    crossing = (va < 0) != (vb < 0)
    t = np.where(crossing, va / np.where(crossing, va - vb, 1.0), 0.0)
    pa, pb = _CORNERS[_EDGES[:, 0]], _CORNERS[_EDGES[:, 1]]
    points = pa[None] + t[..., None] * (pb - pa)[None]
    local_vertex = (points * crossing[..., None]).sum(1) / crossing.sum(1, keepdims=True)
    vertices = (coords[cell] + local_vertex + 0.5) * voxel
    vertex_of = np.full(len(keys), -1, np.int64)
    vertex_of[np.flatnonzero(cell)] = np.arange(cell.sum())

    quads = [_axis_quads(axis, coords, values, vertices, vertex_of, lookup) for axis in range(3)]
    quad = np.concatenate(quads) if quads else np.zeros((0, 4), np.int64)
    faces = np.concatenate([quad[:, [0, 1, 2]], quad[:, [0, 2, 3]]])
    used = np.unique(faces)
    remap = np.full(len(vertices), -1, np.int64)
    remap[used] = np.arange(len(used))
    return vertices[used], remap[faces]


def _axis_quads(axis: int, coords: np.ndarray, values: np.ndarray, vertices: np.ndarray, vertex_of: np.ndarray,
                lookup) -> np.ndarray:
    """(Q, 4) vertex ids of the quads around the voxel edges along ``axis`` whose TSDF changes sign,
    each turned so its normal points from negative to positive. ``coords`` (N, 3) and ``values``
    (N,) are the sorted voxels, ``vertex_of`` (N,) each cell's vertex (−1: none), ``lookup(c)`` →
    (index, found) of (M, 3) voxel coordinates."""
    step = np.eye(3, dtype=np.int64)[axis]
    j, found = lookup(coords + step)
    change = found & ((values < 0) != (values[j] < 0))
    base = coords[change]
    a1, a2 = [np.eye(3, dtype=np.int64)[k] for k in range(3) if k != axis]
    ids = []
    ok = np.ones(len(base), bool)
    for corner in (base, base - a1, base - a1 - a2, base - a2):
        i, f = lookup(corner)
        v = np.where(f, vertex_of[i], -1)
        ok &= v >= 0
        ids.append(v)
    quad = np.stack(ids, 1)[ok]
    outward = np.where(values[change][ok] < 0, 1.0, -1.0)[:, None] * step[None]  # negative → positive
    p = vertices[quad]
    normal = np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1])
    flip = np.sum(normal * outward, axis=1) < 0
    quad[flip] = quad[flip][:, ::-1]
    return quad


def fuse_open3d(depths: list[np.ndarray], cameras: list[Camera], config: SurfaceConfig,
                plan: GridPlan | None = None):
    """Open3D ``VoxelBlockGrid`` TSDF and its marching cubes: vertices, faces, info.

    The grid holds ``plan``'s blocks with headroom (``plan_grid`` refuses a grid over the
    memory budget before this allocates). Open3D runs in a child process
    (``phirie_jax.native.run_isolated``): a crash in it raises ``NativeLibraryError``
    instead of ending the pipeline. (The legacy ``ScalableTSDFVolume`` of the open3d 0.20
    wheel returns empty meshes even for Open3D's own RGB-D sample, so the tensor API is used.)
    """
    from phirie_jax.native import run_isolated

    plan = plan or plan_grid(depths, cameras, config)
    block_count = allocated_blocks(len(plan.blocks), "open3d")
    Ks, poses = [], []
    for cam in cameras:
        K = cam.K.copy()
        K[:2, 2] -= 0.5  # Open3D counts pixel centres at integers (see phirie_jax.io.rgbd)
        Ks.append(K)
        poses.append(cam.world_to_camera)
    t0 = time.perf_counter()
    vertices, faces, timings = run_isolated(
        "Open3D", _open3d_tsdf, depths, np.stack(Ks), np.stack(poses), config, block_count,
        description="VoxelBlockGrid fusion")
    timings["child_s"] = time.perf_counter() - t0
    return vertices, faces, {**timings, "blocks": len(plan.blocks), "block_count": block_count}


def _open3d_tsdf(depths: list[np.ndarray], Ks: np.ndarray, poses: np.ndarray, config: SurfaceConfig,
                 block_count: int):
    """(In the child process.) Ks (F, 3, 3) with integer pixel centres, poses (F, 4, 4) world → camera."""
    import open3d as o3d
    import open3d.core as o3c

    t0 = time.perf_counter()
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32), attr_channels=((1), (1)),
        voxel_size=config.voxel, block_resolution=config.block, block_count=block_count,
        device=o3c.Device("CPU:0"))
    multiplier = config.truncation / config.voxel
    for depth, K, pose in zip(depths, Ks, poses):
        image = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth, np.float32)))
        K, extrinsic = o3c.Tensor(K, o3c.float64), o3c.Tensor(pose, o3c.float64)
        coords = grid.compute_unique_block_coordinates(image, K, extrinsic, 1.0, config.depth_max,
                                                       trunc_voxel_multiplier=multiplier)
        grid.integrate(coords, image, K, extrinsic, 1.0, config.depth_max, trunc_voxel_multiplier=multiplier)
    t1 = time.perf_counter()
    mesh = grid.extract_triangle_mesh(weight_threshold=config.min_weight)
    t2 = time.perf_counter()
    return (mesh.vertex.positions.numpy().astype(np.float64), mesh.triangle.indices.numpy().astype(np.int64),
            {"fuse_s": t1 - t0, "extract_s": t2 - t1})


def snap_to_centres(vertices: np.ndarray, faces: np.ndarray, centres: np.ndarray, radius: float,
                    neighbours: int) -> tuple[np.ndarray, np.ndarray]:
    """Move each vertex along its normal by the median normal offset of its nearest
    Gaussian centres (≤ ``radius`` away). Returns the vertices (V, 3) and the offsets (V,)."""
    import trimesh
    from scipy.spatial import cKDTree

    if len(centres) == 0 or len(vertices) == 0:
        return vertices, np.zeros(len(vertices))
    normals = trimesh.Trimesh(vertices, faces, process=False).vertex_normals
    dist, idx = cKDTree(centres).query(vertices, k=neighbours, distance_upper_bound=radius, workers=-1)
    dist, idx = dist.reshape(len(vertices), -1), idx.reshape(len(vertices), -1)
    found = np.isfinite(dist)
    along = np.einsum("vkc,vc->vk", centres[np.minimum(idx, len(centres) - 1)] - vertices[:, None], normals)
    # median over the found neighbours: sort with the missing ones last, pick the middle
    along = np.sort(np.where(found, along, np.inf), axis=1)
    count = found.sum(1)
    lo = np.take_along_axis(along, np.maximum((count - 1) // 2, 0)[:, None], 1)[:, 0]
    hi = np.take_along_axis(along, np.maximum(count // 2, 0)[:, None], 1)[:, 0]
    offset = np.where(count > 0, 0.5 * (lo + hi), 0.0)
    return vertices + offset[:, None] * normals, offset


def fuse_depths(depths: list[np.ndarray], cameras: list[Camera], config: SurfaceConfig) -> SurfaceMesh:
    """Fuse depth maps (H, W) in metres (0 = no measurement) seen by ``cameras`` into a mesh.

    Raises ``SurfaceTooLargeError`` (before allocating) when the grid would exceed
    ``config.memory_budget_gb`` and ``NativeLibraryError`` when Open3D crashes."""
    depths = [np.where((d > 0) & (d <= config.depth_max) & np.isfinite(d), d, 0.0).astype(np.float32)
              for d in depths]
    if not depths or not any(np.any(d > 0) for d in depths):
        raise ValueError("no valid depth to fuse (every pixel empty or beyond depth_max)")
    t0 = time.perf_counter()
    plan = plan_grid(depths, cameras, config)
    info = {"backend": config.backend, "voxel": config.voxel, "truncation": config.truncation,
            "frames": len(depths), "depth_bounds": None if plan.bounds is None else np.round(plan.bounds, 4).tolist(),
            "grid_gb": round(plan.bytes_needed / 1e9, 3), "plan_s": time.perf_counter() - t0}
    if config.backend == "open3d":
        vertices, faces, timings = fuse_open3d(depths, cameras, config, plan)
    else:
        blocks, tsdf, weight, timings = fuse_jax(depths, cameras, config, plan)
        t0 = time.perf_counter()
        vertices, faces = surface_nets(blocks, tsdf, weight, config.voxel, config.min_weight)
        timings["extract_s"] = time.perf_counter() - t0
    info.update(timings, vertices=len(vertices), faces=len(faces))
    return SurfaceMesh(vertices, faces, info)
