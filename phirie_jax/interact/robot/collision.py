"""The robot's contacts in the model batched worlds run on MJX: finger pads only.

MJX checks every geom pair its contact filter allows, every step, and traces one collision
function per distinct (geom types, mesh ids, condim) group (``mujoco.mjx`` collision driver).
The Panda as merged collides through a mesh per link (nine meshes that meet each other and every
object) and thirteen capsules and boxes per finger: hundreds of pairs and dozens of distinct
mesh–mesh functions, which MJX takes longer to compile than the experiments it serves.

The MJX model keeps what a pick-and-place needs, as MJX users do:

* every robot geom (links, stand, the fingers' own geoms) stops colliding (contype =
  conaffinity = 0): the scripted arm and a policy's arm move above the scene, and the links
  never touch an object in the scripted task;
* each finger (a body driven by a gripper joint) collides through one box, the bounding box of
  its colliding geoms in the finger's frame, with their friction, solver settings and contact
  bits (``PAD_CONDIM`` for the contact dimension): the pads grip the objects and rest on the
  support as the capsules do.

With objects colliding through one convex hull each (``interact.mjx_model``), the object being
grasped is the exception (``grip_parts_spec``): a hull closes a bottle's neck into a cone, which
closing fingers squeeze the bottle down and out of (the demo scene's bottle missed its goal by
6–9 cm in every such episode, in MuJoCo C as in MJX). Its exported parts meet the finger pads
and nothing else (contact bit ``GRIP_BIT``), its hull meets everything but the pads: a handful of
extra collision functions (one per part) for a grip on the real shape.

The single MuJoCo C environment keeps the full model; ``experiments/robot_eval.py`` reports how
often the two agree on the scripted task's outcome.
"""

from __future__ import annotations

import numpy as np

from phirie_jax.interact.robot.appearance import geom_mesh
from phirie_jax.rotations import quat_to_matrix

PAD_SUFFIX = "_pad"
GRIP_BIT = 2              # the contact bit only the finger pads and the grasped object's parts share
# The pads' contact dimension: sliding friction only, as the objects' contacts with the support.
# Two flat pads touch an object at several points each, which resists twisting; the capsules'
# torsional friction (condim 6, coefficient 0.5) on flat boxes flung the demo bottle out of the
# grip in MuJoCo C (8 of 8 episodes with condim 4 or 6, 2 of 8 with 3, on its hull). Pad–object
# contacts then share one MJX collision function per object with the support's (the key holds
# condim).
PAD_CONDIM = 3


def colliding_geoms(model, body: int) -> list[int]:
    """Geoms of ``body`` with a contact bit set."""
    return [g for g in range(model.ngeom) if model.geom_bodyid[g] == body
            and (model.geom_contype[g] or model.geom_conaffinity[g])]


def finger_bodies(model, robot) -> list[int]:
    """Bodies the gripper joints move (each finger once, in joint order)."""
    out = []
    for adr in robot.gripper_qpos:
        body = int(model.jnt_bodyid[int(np.flatnonzero(model.jnt_qposadr == adr)[0])])
        if body not in out:
            out.append(body)
    return out


def extreme_points(model, geom: int) -> np.ndarray:
    """(P, 3) points of a geom's surface, in its body's frame, whose bounding box is the geom's:
    exact for spheres, capsules, boxes and meshes; the tessellated surface for other shapes."""
    import mujoco

    kind, size = int(model.geom_type[geom]), model.geom_size[geom]
    rot = quat_to_matrix(model.geom_quat[geom])
    centre = model.geom_pos[geom]
    axes = np.vstack([np.eye(3), -np.eye(3)])
    if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        return centre + size[0] * axes
    if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:  # each end's sphere, farthest along ±x, ±y, ±z
        ends = centre + np.outer([1.0, -1.0], size[1] * rot[:, 2])
        return (ends[:, None, :] + size[0] * axes[None]).reshape(-1, 3)
    if kind == mujoco.mjtGeom.mjGEOM_BOX:
        corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * size[:3]
        return centre + corners @ rot.T
    mesh = geom_mesh(model, geom)
    return np.zeros((0, 3)) if mesh is None else np.asarray(mesh.vertices)


def pad_box(model, body: int) -> tuple[np.ndarray, np.ndarray]:
    """(3,) centre and (3,) half extents of the bounding box of a body's colliding geoms, in the
    body's frame."""
    points = [extreme_points(model, g) for g in colliding_geoms(model, body)]
    points = [p for p in points if len(p)]
    if not points:
        raise ValueError(f"body {model.body(body).name} has no colliding geometry for a finger pad")
    points = np.concatenate(points)
    low, high = points.min(0), points.max(0)
    return 0.5 * (low + high), 0.5 * (high - low)


def pad_collision_spec(spec, model, robot):
    """Edit ``spec`` (the compiled ``model``'s source, robot merged) so the robot collides only
    through one box per finger (module docstring), in place; returns it."""
    import mujoco

    fingers = finger_bodies(model, robot)
    pads = {}
    for body in fingers:
        geoms = colliding_geoms(model, body)
        if not geoms:
            continue
        first = geoms[0]
        pads[body] = (pad_box(model, body), first)
    for body in robot.bodies:
        for geom in spec.body(model.body(body).name).geoms:
            geom.contype, geom.conaffinity = 0, 0
    for body, ((centre, half), first) in pads.items():
        name = model.body(body).name
        spec.body(name).add_geom(
            name=name + PAD_SUFFIX, type=mujoco.mjtGeom.mjGEOM_BOX, size=half.tolist(), pos=centre.tolist(),
            friction=model.geom_friction[first].tolist(), solref=model.geom_solref[first].tolist(),
            solimp=model.geom_solimp[first].tolist(), condim=PAD_CONDIM,
            contype=int(model.geom_contype[first]), conaffinity=int(model.geom_conaffinity[first]),
            margin=0.0, gap=0.0, group=3, rgba=[0, 0, 0, 0])
    return spec


def pad_names(model, robot) -> list[str]:
    """Names of the finger pads ``pad_collision_spec`` adds, for the fingers that have them."""
    return [model.body(b).name + PAD_SUFFIX for b in finger_bodies(model, robot) if colliding_geoms(model, b)]


def grip_parts_spec(spec, model, body: str, pads: list[str]):
    """Edit ``spec`` — ``model``'s source with ``body``'s hull added (``mjx_model.hull_collision_spec``)
    and the finger ``pads`` — so the pads meet ``body``'s exported parts, and its hull meets
    everything but the pads (module docstring), in place; returns it."""
    import mujoco

    from phirie_jax.interact.mjx_model import HULL_SUFFIX

    body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    parts = set(colliding_geoms(model, body_id))
    originals = [g for g in range(model.ngeom) if model.geom_bodyid[g] == body_id]  # the spec's order
    for geom in spec.body(body).geoms:
        if geom.name == body + HULL_SUFFIX:
            geom.conaffinity = 0                      # its contype still meets support, floor, objects
    for index, geom in zip(originals, spec.body(body).geoms):
        if index in parts:
            geom.contype, geom.conaffinity = 0, GRIP_BIT
    for name in pads:
        spec.geom(name).contype |= GRIP_BIT
    return spec
