"""First-hit ray casting against the scene surface (Open3D's ``RaycastingScene``).

Rays are cast through pixel centres (i + 0.5, j + 0.5) with directions whose camera-z
component is 1, so the hit parameter *is* the depth along the optical axis.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from phirie_jax.types import Camera


@dataclasses.dataclass(frozen=True)
class Hits:
    """Where rays first meet the surface. Misses have depth = inf and face = −1."""

    points: np.ndarray  # (R, 3) world hit points (nan for misses)
    depth: np.ndarray   # (R,) camera-z depth of the hit
    face: np.ndarray    # (R,) int64 triangle index
    bary: np.ndarray    # (R, 3) barycentric weights of the face's three vertices
    normal: np.ndarray  # (R, 3) unit face normal, turned towards the ray origin

    @property
    def hit(self) -> np.ndarray:
        return np.isfinite(self.depth)


def pixel_grid(width: int, height: int, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Integer (rows, cols) of the pixels on a stride, offset to the middle of each cell."""
    rows = np.arange(min(stride // 2, height - 1), height, stride)
    cols = np.arange(min(stride // 2, width - 1), width, stride)
    return rows, cols


def working_pixel_grid(width: int, height: int, stride: int = 1, working_width: int = 0
                       ) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the photo's pixels sampled when observing at ``working_width``.

    A photo at most ``working_width`` wide (or ``working_width`` 0) gives ``pixel_grid``
    itself. A wider one gives, for each pixel of the image scaled to ``working_width`` on
    ``stride``, the photo pixel under its centre: no more rows and columns than the working
    image has, and every ray still passes through a photo pixel's centre.
    """
    if working_width <= 0 or width <= working_width:
        return pixel_grid(width, height, stride)
    factor = working_width / width
    rows, cols = pixel_grid(working_width, max(1, int(round(height * factor))), stride)
    return (np.minimum(((rows + 0.5) / factor).astype(np.int64), height - 1),
            np.minimum(((cols + 0.5) / factor).astype(np.int64), width - 1))


def nearest_index(sampled: np.ndarray, size: int) -> np.ndarray:
    """(size,) index into the sorted pixel positions ``sampled`` (S ≥ 1,) of the nearest to each of 0..size−1."""
    target = np.arange(size)
    right = np.minimum(np.searchsorted(sampled, target), len(sampled) - 1)
    left = np.maximum(right - 1, 0)
    return np.where(np.abs(target - sampled[left]) <= np.abs(sampled[right] - target), left, right)


def pixel_rays(camera: Camera, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World rays through pixel centres of rows × cols: origins (R, 3), directions (R, 3) with z_cam = 1.

    R = len(rows) · len(cols), row-major.
    """
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    pix = np.stack([cc.ravel() + 0.5, rr.ravel() + 0.5, np.ones(rr.size)], axis=1)
    dirs_cam = pix @ np.linalg.inv(camera.K).T
    c2w = camera.camera_to_world
    dirs = dirs_cam @ c2w[:3, :3].T
    return np.broadcast_to(c2w[:3, 3], dirs.shape).copy(), dirs


class Raycaster:
    """A triangle mesh prepared once for many ray queries.

    working_width: ``cast_camera`` of a wider photo casts only the rays of the image scaled to
    this width (``working_pixel_grid``) and gives every requested pixel the hit of the nearest
    cast one; 0 casts every requested pixel."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, working_width: int = 0):
        import open3d as o3d

        self.vertices = np.asarray(vertices, np.float64)
        self.faces = np.asarray(faces, np.int64)
        self.working_width = int(working_width)
        if len(self.faces) == 0:
            raise ValueError("cannot ray cast an empty mesh")
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor(self.vertices.astype(np.float32)),
                                  o3d.core.Tensor(self.faces.astype(np.uint32)))

    @classmethod
    def from_trimesh(cls, mesh, working_width: int = 0) -> Raycaster:
        return cls(mesh.vertices, mesh.faces, working_width)

    def cast(self, origins: np.ndarray, directions: np.ndarray, chunk: int = 1 << 20) -> Hits:
        """First hits of rays (R, 3), (R, 3); ``depth`` is in units of the direction's length."""
        import open3d as o3d

        parts = []
        for start in range(0, len(origins), chunk):
            rays = np.concatenate([origins[start:start + chunk], directions[start:start + chunk]], axis=1)
            ans = self._scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
            parts.append({k: ans[k].numpy() for k in ("t_hit", "primitive_ids", "primitive_uvs",
                                                       "primitive_normals")})
        if not parts:
            empty = np.zeros((0, 3))
            return Hits(empty, np.zeros(0), np.zeros(0, np.int64), empty, empty)
        t = np.concatenate([p["t_hit"] for p in parts]).astype(np.float64)
        face = np.concatenate([p["primitive_ids"] for p in parts]).astype(np.int64)
        uv = np.concatenate([p["primitive_uvs"] for p in parts]).astype(np.float64)
        normal = np.concatenate([p["primitive_normals"] for p in parts]).astype(np.float64)
        hit = np.isfinite(t)
        face[~hit] = -1
        # Open3D's (u, v) weight vertices 1 and 2; vertex 0 gets the rest
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        # the hit point from the exact (float64) ray, not Open3D's float32 sum
        points = np.where(hit[:, None], origins + np.where(hit, t, 0.0)[:, None] * directions, np.nan)
        flip = np.sum(normal * directions, axis=1) > 0
        normal[flip] *= -1
        return Hits(points, t, face, bary, normal)

    def cast_camera(self, camera: Camera, stride: int = 1) -> tuple[Hits, np.ndarray, np.ndarray]:
        """Hits of the rays through the camera's pixels on ``stride`` (R = len(rows) · len(cols),
        row-major); also their rows, cols. Past ``working_width`` the rays of the working grid
        are cast and each pixel takes the hit of the nearest of them."""
        rows, cols = pixel_grid(camera.width, camera.height, stride)
        cast_rows, cast_cols = working_pixel_grid(camera.width, camera.height, stride, self.working_width)
        hits = self.cast(*pixel_rays(camera, cast_rows, cast_cols))
        if len(cast_rows) == len(rows) and len(cast_cols) == len(cols):
            return hits, rows, cols
        r = nearest_index(cast_rows, camera.height)[rows]
        c = nearest_index(cast_cols, camera.width)[cols]
        pick = (r[:, None] * len(cast_cols) + c[None, :]).ravel()
        return Hits(hits.points[pick], hits.depth[pick], hits.face[pick], hits.bary[pick], hits.normal[pick]), rows, cols

    def within(self, points: np.ndarray, radius: float) -> np.ndarray:
        """(N,) bool: the (N, 3) points within ``radius`` of the surface or inside it (ray parity
        over three rays; meant for closed meshes)."""
        import open3d as o3d

        if len(points) == 0:
            return np.zeros(0, bool)
        query = o3d.core.Tensor(np.asarray(points, np.float32))
        near = self._scene.compute_distance(query).numpy() <= radius
        return near | (self._scene.compute_occupancy(query, nsamples=3).numpy() > 0.5)

    def deep_inside(self, points: np.ndarray, depth: float) -> np.ndarray:
        """(N,) bool: the (N, 3) points inside the (closed) surface and more than ``depth`` from it."""
        import open3d as o3d

        if len(points) == 0:
            return np.zeros(0, bool)
        query = o3d.core.Tensor(np.asarray(points, np.float32))
        far = self._scene.compute_distance(query).numpy() > depth
        return far & (self._scene.compute_occupancy(query, nsamples=3).numpy() > 0.5)

    def seen_through(self, points: np.ndarray, camera: Camera, tolerance: float) -> np.ndarray:
        """(N,) bool: the camera's ray through each (N, 3) point meets the surface more than
        ``tolerance`` beyond it, i.e. the camera saw past the point (it is free space)."""
        centre = camera.center
        offset = np.asarray(points, np.float64) - centre
        distance = np.linalg.norm(offset, axis=1)
        hits = self.cast(np.broadcast_to(centre, offset.shape).copy(), offset / np.maximum(distance, 1e-12)[:, None])
        return hits.depth > distance + tolerance   # misses (inf) count: the camera saw past it

    def faces_camera(self, points: np.ndarray, camera: Camera, tolerance: float) -> np.ndarray:
        """(N,) bool: each (N, 3) point is on the side of this surface the camera sees: the camera's
        ray meets the surface no nearer than ``tolerance`` before the point."""
        return self.seen_through(points, camera, -tolerance)

    def depth_map(self, camera: Camera) -> np.ndarray:
        """(H, W) camera-z depth of the first hit per pixel, 0 where the ray misses."""
        hits, _, _ = self.cast_camera(camera)
        return np.where(hits.hit, hits.depth, 0.0).reshape(camera.height, camera.width)
