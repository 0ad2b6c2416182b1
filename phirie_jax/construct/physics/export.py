"""Simulator files: collision parts (OBJ), ``object.urdf`` per object, ``scene.xml`` (MJCF).

Collision parts are written in the canonical mesh frame (DESIGN.md "Contracts"), so the
manifest's ``pose`` places them exactly as it places ``mesh.obj``; a pose's scale becomes
the mesh ``scale`` attribute in MJCF and URDF. Both files carry the same explicit inertial
(``physics.MassProperties`` of the scaled parts): the same mass, centre of mass and tensor.

``scene.xml``: gravity along −up of the scene, the background support geoms, and one free
body per object named ``object_<id>``, placed at S_i(0) (the pose's rotation and translation).
Every path inside is relative to the output folder, where ``scene.xml`` lives.

PyBullet replaces a URDF's inertia by its collision shapes' bounding boxes unless loaded with
``flags=pybullet.URDF_USE_INERTIA_FROM_FILE``; with it, mass, centre of mass and principal
moments are the ones written here (tested).
"""

from __future__ import annotations

import dataclasses
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from phirie_jax.construct.physics.collision import ConvexPart
from phirie_jax.construct.physics.config import PhysicsConfig
from phirie_jax.construct.physics.priors import MassProperties, Priors
from phirie_jax.geometry import split_sim3
from phirie_jax.io.atomic import write_files, write_text

GRAVITY = 9.81
TORSIONAL_FRICTION, ROLLING_FRICTION = 0.005, 0.0001   # MuJoCo's defaults


@dataclasses.dataclass(frozen=True)
class SceneObject:
    """What ``scene.xml`` needs of one accepted object."""

    id: int
    collision: tuple[str, ...]     # part paths relative to the output folder
    pose: np.ndarray               # (4, 4) Sim(3) canonical → scene
    mass: MassProperties           # body frame = canonical frame, scale applied
    priors: Priors


@dataclasses.dataclass(frozen=True)
class BackgroundGeom:
    name: str
    type: str                      # "plane" or "box"
    pos: np.ndarray                # (3,) scene frame
    quat: np.ndarray               # (4,) wxyz, scene frame
    size: np.ndarray               # (3,) MuJoCo half sizes (plane: drawn half extent, spacing)
    source: str

    def record(self) -> dict:
        return {"name": self.name, "type": self.type, "pos": self.pos, "quat": self.quat, "size": self.size,
                "source": self.source}


def body_name(object_id: int) -> str:
    return f"object_{object_id}"


def _f(values) -> str:
    return " ".join(f"{float(v) + 0.0:.9g}" for v in np.ravel(values))   # + 0.0: no "-0"


def obj_text(part: ConvexPart) -> str:
    lines = [f"# phirie convex collision part: {len(part.vertices)} vertices, canonical frame, metres\n"]
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in part.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in part.faces]
    return "".join(lines)


def write_parts(out_dir: Path, object_id: int, parts: tuple[ConvexPart, ...]) -> list[str]:
    """``objects/<id>/collision/part_NN.obj`` for each part (all written, then renamed); relative paths."""
    folder = Path("objects") / str(object_id) / "collision"
    names = [f"part_{k:02d}.obj" for k in range(len(parts))]
    for stale in (out_dir / folder).glob("part_*.obj") if (out_dir / folder).is_dir() else ():
        if stale.name not in names:
            stale.unlink()
    write_files(out_dir / folder, {n: obj_text(p).encode("ascii") for n, p in zip(names, parts)})
    return [str(folder / n) for n in names]


def read_part(path: Path) -> ConvexPart:
    """A collision part OBJ back (vertices and triangles)."""
    verts, faces = [], []
    for line in path.read_text(encoding="ascii").splitlines():
        if line.startswith("v "):
            verts.append([float(x) for x in line.split()[1:4]])
        elif line.startswith("f "):
            faces.append([int(tok.split("/")[0]) - 1 for tok in line.split()[1:4]])
    return ConvexPart(np.asarray(verts, np.float64).reshape(-1, 3), np.asarray(faces, np.int64).reshape(-1, 3))


def _inertia_attrs(m: MassProperties) -> dict[str, str]:
    i = m.inertia
    return {"ixx": f"{i[0, 0]:.9g}", "ixy": f"{i[0, 1]:.9g}", "ixz": f"{i[0, 2]:.9g}",
            "iyy": f"{i[1, 1]:.9g}", "iyz": f"{i[1, 2]:.9g}", "izz": f"{i[2, 2]:.9g}"}


def _xml(root: ET.Element) -> str:
    ET.indent(root, space="  ")
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def object_urdf(object_id: int, mesh: str, parts: list[str], scale: float, mass: MassProperties,
                pr: Priors) -> str:
    """URDF of one object; ``mesh`` and ``parts`` relative to the URDF's folder."""
    robot = ET.Element("robot", name=body_name(object_id))
    link = ET.SubElement(robot, "link", name=body_name(object_id))
    contact = ET.SubElement(link, "contact")   # PyBullet's extension
    ET.SubElement(contact, "lateral_friction", value=f"{pr.friction:g}")
    ET.SubElement(contact, "restitution", value=f"{pr.restitution:g}")
    inertial = ET.SubElement(link, "inertial")
    ET.SubElement(inertial, "origin", xyz=_f(mass.com), rpy="0 0 0")
    ET.SubElement(inertial, "mass", value=f"{mass.mass:.9g}")
    ET.SubElement(inertial, "inertia", **_inertia_attrs(mass))
    s = _f([scale] * 3)
    visual = ET.SubElement(link, "visual")
    ET.SubElement(ET.SubElement(visual, "geometry"), "mesh", filename=mesh, scale=s)
    for part in parts:
        collision = ET.SubElement(link, "collision")
        ET.SubElement(ET.SubElement(collision, "geometry"), "mesh", filename=part, scale=s)
    return _xml(robot)


def write_urdf(out_dir: Path, object_id: int, mesh: str | None, parts: list[str], scale: float,
               mass: MassProperties, pr: Priors) -> str:
    folder = Path("objects") / str(object_id)
    rel = lambda p: str(Path(p).relative_to(folder))  # noqa: E731
    text = object_urdf(object_id, rel(mesh) if mesh else rel(parts[0]), [rel(p) for p in parts], scale, mass, pr)
    write_text(out_dir / folder / "object.urdf", text)
    return str(folder / "object.urdf")


def _contact_attrs(pr: Priors) -> dict[str, str]:
    return {"friction": _f([pr.friction, TORSIONAL_FRICTION, ROLLING_FRICTION]), "solref": _f(pr.solref),
            "solimp": _f(pr.solimp)}


def scene_mjcf(objects: list[SceneObject], background: list[BackgroundGeom], up: np.ndarray,
               config: PhysicsConfig) -> str:
    """``scene.xml`` text (paths relative to the folder it is written to)."""
    from phirie_jax.construct.physics.priors import priors as default_priors

    dt = config.drop_test
    root = ET.Element("mujoco", model="phirie_scene")
    ET.SubElement(root, "compiler", angle="radian", autolimits="true")
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    ET.SubElement(root, "option", timestep=f"{dt.timestep:.9g}", gravity=_f(-GRAVITY * up),
                  iterations=str(config.scene_solver_iterations),
                  ls_iterations=str(config.scene_line_search_iterations),
                  tolerance=f"{dt.tolerance:g}")
    asset = ET.SubElement(root, "asset")
    world = ET.SubElement(root, "worldbody")
    ET.SubElement(world, "light", name="sun", directional="true", pos=_f(3 * up), dir=_f(-up))
    ground = _contact_attrs(default_priors(None, config))
    for g in background:
        ET.SubElement(world, "geom", name=g.name, type=g.type, pos=_f(g.pos), quat=_f(g.quat), size=_f(g.size),
                      rgba="0.6 0.6 0.6 1", **ground)
    for obj in objects:
        scale, rot, trans = split_sim3(obj.pose)
        name = body_name(obj.id)
        quat = Rotation.from_matrix(rot).as_quat(scalar_first=True)
        body = ET.SubElement(world, "body", name=name, pos=_f(trans), quat=_f(quat))
        ET.SubElement(body, "freejoint", name=name)
        i = obj.mass.inertia
        ET.SubElement(body, "inertial", pos=_f(obj.mass.com), mass=f"{obj.mass.mass:.9g}",
                      fullinertia=_f([i[0, 0], i[1, 1], i[2, 2], i[0, 1], i[0, 2], i[1, 2]]))
        for k, path in enumerate(obj.collision):
            mesh = f"{name}_part_{k:02d}"
            ET.SubElement(asset, "mesh", name=mesh, file=path, scale=_f([scale] * 3))
            ET.SubElement(body, "geom", name=mesh, type="mesh", mesh=mesh, **_contact_attrs(obj.priors))
    return _xml(root)


def settle_scene(scene_xml: Path, seconds: float = 2.0) -> dict[str, float]:
    """Load ``scene.xml`` in MuJoCo, simulate ``seconds`` freely and return each object body's
    centre-of-mass displacement (m), by body name."""
    import mujoco

    model = mujoco.MjModel.from_xml_path(str(scene_xml))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    bodies = [b for b in range(1, model.nbody) if model.body(b).name.startswith("object_")]
    start = data.xipos[bodies].copy()
    mujoco.mj_step(model, data, nstep=int(round(seconds / model.opt.timestep)))
    moved = np.linalg.norm(data.xipos[bodies] - start, axis=1)
    return {model.body(b).name: float(d) for b, d in zip(bodies, moved)}
