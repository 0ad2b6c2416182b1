"""The MuJoCo model the batched worlds run on MJX.

MJX checks every geom pair its contact filter allows, every step, and traces one collision
function per distinct (geom types, mesh ids) pair. A converted scene's objects carry up to 16
convex parts each (CoACD), so six objects already make about a thousand distinct part–part
functions: the program takes longer to compile than the experiment it serves. Two models:

    "parts"  the exported ``scene.xml`` as it is — exactly the single environment's contacts,
             compile time growing with the square of the part count;
    "hull"   each object collides through one convex hull of its parts (≤ ``max_vertices``),
             the parts kept only as non-colliding geoms; contacts with the supports and between
             objects are those of the hulls. Mass, inertia and centre of mass are the exported
             ``<inertial>``'s, unchanged. Resting on a support is unchanged wherever the parts'
             lowest envelope is convex (flat bottoms, rims); an object can no longer enter another's
             concavity (a fruit cannot sit inside a bowl).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from phirie_jax.construct.physics.collision import hull_part
from phirie_jax.rotations import quat_to_matrix

CollisionModel = Literal["parts", "hull"]
HULL_SUFFIX = "_hull"


def multi_part(model, body_id: int) -> bool:
    """Whether a body collides through more than one geom, all of them meshes."""
    import mujoco

    geoms = np.flatnonzero((model.geom_bodyid == body_id) & ((model.geom_contype | model.geom_conaffinity) > 0))
    return len(geoms) > 1 and bool(np.all(model.geom_type[geoms] == mujoco.mjtGeom.mjGEOM_MESH))


def body_frame_vertices(model, body_id: int) -> np.ndarray:
    """(V, 3) vertices of every mesh geom of a body, in the body's frame."""
    import mujoco

    out = []
    for g in np.flatnonzero(model.geom_bodyid == body_id):
        if model.geom_type[g] != mujoco.mjtGeom.mjGEOM_MESH:
            continue
        mesh = model.geom_dataid[g]
        start, count = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
        out.append(model.mesh_vert[start:start + count] @ quat_to_matrix(model.geom_quat[g]).T + model.geom_pos[g])
    return np.concatenate(out) if out else np.zeros((0, 3))


def hull_collision_spec(spec, model, bodies: list[str], max_vertices: int = 64):
    """Edit ``spec`` (the compiled ``model``'s source) to the "hull" collision model, in place.

    Each named body (its geoms: meshes, ``multi_part``) gets one mesh geom, the convex hull of
    its parts; its other geoms stop
    colliding (contype = conaffinity = 0) and the hull takes their friction and solver
    parameters.
    """
    import mujoco

    for name in bodies:
        body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
        part = hull_part(body_frame_vertices(model, body_id), max_vertices)
        body = spec.body(name)
        first = body.geoms[0]
        friction, solref, solimp = first.friction.copy(), first.solref.copy(), first.solimp.copy()
        for geom in body.geoms:
            geom.contype, geom.conaffinity = 0, 0
        spec.add_mesh(name=name + HULL_SUFFIX, uservert=part.vertices.ravel().tolist(),
                      userface=part.faces.ravel().tolist())
        body.add_geom(name=name + HULL_SUFFIX, type=mujoco.mjtGeom.mjGEOM_MESH, meshname=name + HULL_SUFFIX,
                      friction=friction, solref=solref, solimp=solimp, contype=1, conaffinity=1,
                      group=3, rgba=[0, 0, 0, 0])
    return spec
