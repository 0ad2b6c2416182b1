"""A robot drawn by its Gaussians: each link's visual geoms become surface-aligned flat disks.

Done once, from the compiled model: every visual geom of a body (the geoms that do not collide;
a body with none, such as the stand, shows its colliding geoms) is meshed in the body's frame
(mesh assets as compiled, primitives through trimesh), sampled by area at ``spacing`` and turned
into flat disks by the synthetic capture's own code (``synthetic.capture.surface_gaussians``),
coloured by the geom's material or rgba. The untextured links get a view-dependent lobe of
strength ``shading`` about each disk's normal, which shades them by the angle they are seen at
and turns with the link (the SH coefficients are rotated with the body each frame).

The Gaussians live in the body's frame, so the environment places them by the body's simulated
pose like an object's (``Environment``: the body-attached set).
"""

from __future__ import annotations

import numpy as np

from phirie_jax.rotations import quat_to_matrix
from phirie_jax.synthetic.capture import sample_surface, surface_gaussians
from phirie_jax.types import GaussianSplatData

MIN_SAMPLES_AREA = 1e-6   # m²: geoms smaller than this are not drawn


def geom_mesh(model, geom: int):
    """The geom's surface as a trimesh in its body's frame (None for planes, height fields, ...)."""
    import mujoco
    import trimesh

    kind, size = int(model.geom_type[geom]), model.geom_size[geom]
    if kind == mujoco.mjtGeom.mjGEOM_MESH:
        mesh_id = model.geom_dataid[geom]
        vadr, vnum = model.mesh_vertadr[mesh_id], model.mesh_vertnum[mesh_id]
        fadr, fnum = model.mesh_faceadr[mesh_id], model.mesh_facenum[mesh_id]
        mesh = trimesh.Trimesh(model.mesh_vert[vadr:vadr + vnum].copy(), model.mesh_face[fadr:fadr + fnum].copy(),
                               process=False)
    elif kind == mujoco.mjtGeom.mjGEOM_BOX:
        mesh = trimesh.creation.box(extents=2 * size)
    elif kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        mesh = trimesh.creation.icosphere(subdivisions=2, radius=size[0])
    elif kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
        mesh = trimesh.creation.capsule(height=2 * size[1], radius=size[0])
    elif kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
        mesh = trimesh.creation.cylinder(radius=size[0], height=2 * size[1])
    elif kind == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
        mesh = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
        mesh.apply_scale(size)
    else:
        return None
    transform = np.eye(4)
    transform[:3, :3], transform[:3, 3] = quat_to_matrix(model.geom_quat[geom]), model.geom_pos[geom]
    mesh.apply_transform(transform)
    return mesh


def geom_rgb(model, geom: int) -> np.ndarray:
    """(3,) the geom's colour: its material's when it has one, else its own rgba."""
    material = int(model.geom_matid[geom])
    return np.asarray(model.mat_rgba[material][:3] if material >= 0 else model.geom_rgba[geom][:3], np.float64)


def visual_geoms(model, body: int) -> list[int]:
    """The geoms that draw a body: its non-colliding ones, else all of them (none transparent)."""
    geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] == body and model.geom_rgba[g][3] > 0]
    visual = [g for g in geoms if model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0]
    return visual or geoms


def body_gaussians(model, body: int, spacing: float, shading: float, rng: np.random.Generator) -> GaussianSplatData | None:
    """Flat-disk Gaussians on a body's visual surface, in the body's frame (None: nothing drawn)."""
    parts = []
    for geom in visual_geoms(model, body):
        mesh = geom_mesh(model, geom)
        if mesh is None or mesh.area < MIN_SAMPLES_AREA:
            continue
        points, normals = sample_surface(mesh, spacing, rng)
        rgb = geom_rgb(model, geom)
        parts.append(surface_gaussians(points, normals, lambda p, rgb=rgb: np.broadcast_to(rgb, p.shape), points,
                                       spacing, 0, shading, rng).data)
    return GaussianSplatData.join(parts) if parts else None


def robot_gaussians(model, bodies: list[int], spacing: float, shading: float, seed: int
                    ) -> list[tuple[int, GaussianSplatData]]:
    """(body id, Gaussians in its frame) of every drawn body among ``bodies``."""
    rng = np.random.default_rng(seed)
    out = []
    for body in bodies:
        splats = body_gaussians(model, body, spacing, shading, rng)
        if splats is not None:
            out.append((body, splats))
    return out
