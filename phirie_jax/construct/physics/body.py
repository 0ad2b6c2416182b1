"""One object as one MuJoCo free body: the record (``ObjectBody``) and the one builder (``add_body``).

The drop test's models (``droptest.build_model``) and ``scene.xml`` (``mjcf.scene_spec``) both add
their object bodies with ``add_body`` to a ``mujoco.MjSpec``, and ``object.urdf`` is written from
the same record, so an object's inertial and contact parameters exist once:

* inertial: explicit, ``MassProperties`` of the scaled convex parts (mass, centre of mass, full
  tensor), never recomputed by MuJoCo from the meshes;
* contact (``contact``): sliding friction from the priors with MuJoCo's default torsional and
  rolling friction, ``solref`` and ``solimp`` from the priors.

Body frame = the canonical mesh frame with the pose's scale applied (docs/architecture.md "Contracts").
"""

from __future__ import annotations

import dataclasses
import xml.etree.ElementTree as ET
from collections.abc import Sequence

import mujoco
import numpy as np

from phirie_jax.construct.physics.collision import ConvexPart, ghost_part
from phirie_jax.construct.physics.priors import MassProperties, Priors, mass_properties
from phirie_jax.geometry import split_sim3
from phirie_jax.rotations import matrix_to_quat

TORSIONAL_FRICTION, ROLLING_FRICTION = 0.005, 0.0001   # MuJoCo's defaults
BODY_PREFIX = "object_"   # every object body's name starts with this (``body_name``)
WELD_RELPOSE = 3          # a weld's data: anchor (3), then relpose (7: position, quaternion; zeros: from qpos0)


@dataclasses.dataclass(frozen=True)
class ObjectBody:
    """What MuJoCo (and URDF) need of one object's rigid body."""

    id: int | None                 # object id (None: a drop-test candidate, not yet an object)
    parts: tuple[ConvexPart, ...]  # convex parts in the body frame (scale applied), metres
    pose: np.ndarray               # (4, 4) Sim(3) canonical → scene
    mass: MassProperties           # body frame
    priors: Priors
    files: tuple[str, ...] = ()    # the parts' OBJ files (canonical frame, unscaled), relative to the
                                   # output folder (scene.xml's meshes); empty for drop-test candidates
    mounted: bool = False          # welded to the world where it is placed (a head on a wall: ``mount_name``)

    @property
    def scale(self) -> float:
        return split_sim3(self.pose)[0]


def object_body(object_id: int | None, parts: Sequence[ConvexPart], pose: np.ndarray, body_priors: Priors,
                files: Sequence[str] = (), mounted: bool = False) -> ObjectBody:
    """The body of canonical-frame ``parts`` placed by the Sim(3) ``pose`` (4, 4): parts scaled by
    the pose's scale, uniform-density mass properties with the priors' mass."""
    pose = np.asarray(pose, np.float64)
    scale, _, _ = split_sim3(pose)
    scaled = tuple(ConvexPart(scale * p.vertices, p.faces) for p in parts)
    return ObjectBody(object_id, scaled, pose, mass_properties(scaled, body_priors.mass), body_priors,
                      tuple(files), bool(mounted))


def body_name(object_id: int) -> str:
    """The MuJoCo body (and URDF robot/link) name of an object: ``object_<id>``."""
    return f"{BODY_PREFIX}{object_id}"


def mount_name(name: str) -> str:
    """The weld equality that holds a mounted body ``name`` where it is placed: ``<name>_mount``."""
    return f"{name}_mount"


def is_mounted(model: mujoco.MjModel, name: str) -> bool:
    """Whether the body ``name`` of a compiled scene is held by its mount weld (``mount_name``)."""
    return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_EQUALITY, mount_name(name)) >= 0


def contact(pr: Priors) -> dict:
    """MuJoCo contact parameters of a geom with these priors: friction (3,), solref (2,), solimp (5,)."""
    return {"friction": [pr.friction, TORSIONAL_FRICTION, ROLLING_FRICTION], "solref": list(pr.solref),
            "solimp": list(pr.solimp)}


def full_inertia(m: MassProperties) -> list[float]:
    """(6,) MuJoCo's ``fullinertia`` order of the tensor: ixx iyy izz ixy ixz iyz."""
    i = m.inertia
    return [i[0, 0], i[1, 1], i[2, 2], i[0, 1], i[0, 2], i[1, 2]]


def add_body(spec: mujoco.MjSpec, body: ObjectBody, name: str | None = None, placed: bool = True,
             inline: bool = False, pad_to: int = 0):
    """Add ``body`` to ``spec``'s world as a free body; returns the ``MjsBody``. A mounted body
    keeps its free joint (every object has the same 7 qpos) and is held where it is placed by a
    weld equality to the world anchored at its centre of mass (``mount_name``; its relative pose
    is the placement).

    Args:
        spec: the model to add to (meshes go to its assets).
        body: the record.
        name: body name (default ``body_name(body.id)``); its meshes and geoms are ``<name>_part_NN``.
        placed: at the pose's rotation and translation (a scene); else at the origin (the drop
            test sets the free joint's qpos).
        inline: meshes from the scaled parts' vertices (the drop test); else from ``body.files``
            scaled by the pose's scale (``scene.xml``).
        pad_to: ghost parts (``collision.ghost_part`` of the first part) are added up to this many
            parts (the drop test's static part bucket); inline meshes only.
    """
    name = name or body_name(body.id)
    kwargs = {}
    if placed:
        _, rot, trans = split_sim3(body.pose)
        kwargs = {"pos": trans, "quat": matrix_to_quat(rot)}
    b = spec.worldbody.add_body(name=name, **kwargs)
    b.add_freejoint(name=name)
    b.explicitinertial = True
    b.mass = body.mass.mass
    b.ipos = body.mass.com
    b.fullinertia = full_inertia(body.mass)
    names = [f"{name}_part_{k:02d}" for k in range(max(len(body.parts), pad_to))]
    if not inline:
        if len(body.files) != len(names):
            raise ValueError(f"body {name}: {len(body.files)} part files for {len(names)} parts "
                             "(expected one file per part; ghost parts pad inline meshes only)")
        for mesh, path in zip(names, body.files):
            spec.add_mesh(name=mesh, file=path, scale=[body.scale] * 3)
    else:
        parts = list(body.parts) + [ghost_part(body.parts[0])] * (len(names) - len(body.parts))
        for mesh, part in zip(names, parts):
            spec.add_mesh(name=mesh).uservert = part.vertices.ravel()
    for mesh in names:
        b.add_geom(name=mesh, type=mujoco.mjtGeom.mjGEOM_MESH, meshname=mesh, **contact(body.priors))
    if body.mounted:
        weld = spec.add_equality(name=mount_name(name), type=mujoco.mjtEq.mjEQ_WELD, objtype=mujoco.mjtObj.mjOBJ_BODY,
                                 name1="world", name2=name)
        weld.data[:WELD_RELPOSE] = body.mass.com           # anchor (body frame); relpose 0: from the placement
        weld.data[WELD_RELPOSE:WELD_RELPOSE + 7] = 0.0
    return b


def numbers(values) -> str:
    """Numbers as MJCF/URDF attribute text: 9 significant digits, space separated, no "-0"."""
    return " ".join(f"{float(v) + 0.0:.9g}" for v in np.ravel(values))


def xml_text(root: ET.Element) -> str:
    """An XML document's text, indented by two spaces, with its declaration."""
    ET.indent(root, space="  ")
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"
