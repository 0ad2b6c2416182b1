"""``objects/<id>/object.urdf`` (``layout.OBJECT_URDF``) of one object, from its ``ObjectBody``.

One link named ``object_<id>`` (``body.body_name``): the same explicit inertial as ``scene.xml``
(the record's ``MassProperties``: mass, centre of mass and tensor, the same digits), the
visual mesh and the collision part files scaled by the pose's scale, and PyBullet's
``<contact>`` extension with the priors' lateral friction and restitution.

PyBullet replaces a URDF's inertia by its collision shapes' bounding boxes unless loaded with
``flags=pybullet.URDF_USE_INERTIA_FROM_FILE``; with it, mass, centre of mass and principal
moments are the ones written here (tested).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

from phirie_jax import layout
from phirie_jax.construct.physics.body import ObjectBody, body_name, numbers, xml_text
from phirie_jax.io.atomic import write_text


def object_urdf(body: ObjectBody, visual: str, parts: list[str]) -> str:
    """URDF text of one object; ``visual`` and ``parts`` are paths relative to the URDF's folder."""
    robot = ET.Element("robot", name=body_name(body.id))
    link = ET.SubElement(robot, "link", name=body_name(body.id))
    contact = ET.SubElement(link, "contact")   # PyBullet's extension
    ET.SubElement(contact, "lateral_friction", value=f"{body.priors.friction:g}")
    ET.SubElement(contact, "restitution", value=f"{body.priors.restitution:g}")
    inertial = ET.SubElement(link, "inertial")
    m = body.mass
    ET.SubElement(inertial, "origin", xyz=numbers(m.com), rpy="0 0 0")
    ET.SubElement(inertial, "mass", value=f"{m.mass:.9g}")
    i = m.inertia
    ET.SubElement(inertial, "inertia", ixx=f"{i[0, 0]:.9g}", ixy=f"{i[0, 1]:.9g}", ixz=f"{i[0, 2]:.9g}",
                  iyy=f"{i[1, 1]:.9g}", iyz=f"{i[1, 2]:.9g}", izz=f"{i[2, 2]:.9g}")
    scale = numbers([body.scale] * 3)
    visual_element = ET.SubElement(link, "visual")
    ET.SubElement(ET.SubElement(visual_element, "geometry"), "mesh", filename=visual, scale=scale)
    for part in parts:
        collision = ET.SubElement(link, "collision")
        ET.SubElement(ET.SubElement(collision, "geometry"), "mesh", filename=part, scale=scale)
    return xml_text(robot)


def write_urdf(out_dir: Path, body: ObjectBody, mesh: str | None) -> str:
    """Write ``objects/<id>/object.urdf`` (visual: ``mesh``, else the first part file); returns its
    path relative to ``out_dir``. ``mesh`` and ``body.files`` are relative to ``out_dir``."""
    folder = layout.object_dir(body.id)
    rel = lambda p: str(Path(p).relative_to(folder))  # noqa: E731
    text = object_urdf(body, rel(mesh) if mesh else rel(body.files[0]), [rel(p) for p in body.files])
    path = layout.object_file(body.id, layout.OBJECT_URDF)
    write_text(out_dir / path, text)
    return path
