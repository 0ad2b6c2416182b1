"""``scene.xml`` (MJCF, ``layout.SCENE_MJCF``): the scene as one ``mujoco.MjSpec``, written to text.

``scene_spec``: gravity along −up of the scene, the background support geoms (the ground
contact of the default priors), and one free body per object added by ``body.add_body``
(named ``object_<id>``, placed at S_i(0): the pose's rotation and translation; its meshes are
the collision part files scaled by the pose's scale). Every path inside is relative to the
output folder, where ``scene.xml`` lives.

A mounted object (``ObjectBody.mounted``) is also held where it is placed by a weld to the
world (``<equality><weld>``, anchored at its centre of mass).

``spec_xml`` writes the spec's values with 9 significant digits and the explicit
``fullinertia`` the spec was given. MuJoCo's own ``MjSpec.to_xml`` is not used: it compiles the
spec, writes 6 significant digits (the timestep 1/240 becomes 0.00416667) and replaces the
full tensor by principal moments and a rotation.

``settle_scene`` loads the written file in MuJoCo and simulates it freely.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path

import mujoco
import numpy as np

from phirie_jax.construct.physics.body import (
    BODY_PREFIX,
    WELD_RELPOSE,
    ObjectBody,
    add_body,
    contact,
    numbers,
    xml_text,
)
from phirie_jax.construct.physics.config import PhysicsConfig
from phirie_jax.construct.physics.priors import priors
from phirie_jax.construct.physics.supports import BackgroundGeom

GRAVITY = 9.81                          # m/s²
SCENE_MODEL = "phirie_scene"
SUPPORT_RGBA = (0.6, 0.6, 0.6, 1.0)
GEOM_TYPES = {"plane": mujoco.mjtGeom.mjGEOM_PLANE, "box": mujoco.mjtGeom.mjGEOM_BOX,
              "mesh": mujoco.mjtGeom.mjGEOM_MESH}


def scene_spec(bodies: Sequence[ObjectBody], background: Sequence[BackgroundGeom], up: np.ndarray,
               config: PhysicsConfig) -> mujoco.MjSpec:
    """The scene: options, a directional light, the support geoms and every object body.

    Args:
        bodies: the objects, each with its part ``files`` (relative to the output folder).
        background: support geoms in the scene frame (``supports.fit_background``).
        up: (3,) the scene's up direction (gravity is −up).
        config: the scene's solver limits, the drop test's timestep and tolerance, the priors.
    """
    spec = mujoco.MjSpec()
    spec.modelname = SCENE_MODEL
    spec.compiler.degree, spec.compiler.autolimits = False, True
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    opt = spec.option
    opt.timestep, opt.gravity = config.drop_test.timestep, -GRAVITY * up
    opt.iterations, opt.ls_iterations = config.scene_solver_iterations, config.scene_line_search_iterations
    opt.tolerance = config.drop_test.tolerance
    spec.worldbody.add_light(name="sun", type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, pos=3 * up, dir=-up)
    ground = contact(priors(None, config))
    for g in background:
        spec.worldbody.add_geom(name=g.name, type=GEOM_TYPES[g.type], pos=g.pos, quat=g.quat, size=g.size,
                                rgba=SUPPORT_RGBA, **ground)
    for body in bodies:
        add_body(spec, body)
    return spec


def _geom(parent: ET.Element, geom) -> None:
    attrs = {"name": geom.name, "type": next(k for k, v in GEOM_TYPES.items() if v == geom.type)}
    if geom.type == mujoco.mjtGeom.mjGEOM_MESH:
        attrs["mesh"] = geom.meshname
    else:
        attrs.update(pos=numbers(geom.pos), quat=numbers(geom.quat), size=numbers(geom.size),
                     rgba=" ".join(f"{v:g}" for v in geom.rgba))           # float32 colour
    attrs.update(friction=numbers(geom.friction), solref=numbers(geom.solref), solimp=numbers(geom.solimp))
    ET.SubElement(parent, "geom", **attrs)


def _body(parent: ET.Element, body) -> None:
    element = ET.SubElement(parent, "body", name=body.name, pos=numbers(body.pos), quat=numbers(body.quat))
    for joint in body.joints:
        if joint.type != mujoco.mjtJoint.mjJNT_FREE:
            raise ValueError(f"scene body {body.name}: only free joints are written (got {joint.type})")
        ET.SubElement(element, "freejoint", name=joint.name)
    ET.SubElement(element, "inertial", pos=numbers(body.ipos), mass=numbers([body.mass]),
                  fullinertia=numbers(body.fullinertia))
    for geom in body.geoms:
        _geom(element, geom)


def spec_xml(spec: mujoco.MjSpec) -> str:
    """MJCF text of a spec built by ``scene_spec``: its compiler flags, the options it sets
    (timestep, gravity, solver limits, tolerance), file meshes, lights, geoms and free bodies."""
    root = ET.Element("mujoco", model=spec.modelname)
    ET.SubElement(root, "compiler", angle="degree" if spec.compiler.degree else "radian",
                  autolimits=str(bool(spec.compiler.autolimits)).lower())
    opt = spec.option
    ET.SubElement(root, "option", timestep=numbers([opt.timestep]), gravity=numbers(opt.gravity),
                  iterations=str(opt.iterations), ls_iterations=str(opt.ls_iterations),
                  tolerance=numbers([opt.tolerance]))
    asset = ET.SubElement(root, "asset")
    for mesh in spec.meshes:
        ET.SubElement(asset, "mesh", name=mesh.name, file=mesh.file, scale=numbers(mesh.scale))
    world = ET.SubElement(root, "worldbody")
    for light in spec.worldbody.lights:
        directional = str(light.type == mujoco.mjtLightType.mjLIGHT_DIRECTIONAL).lower()
        ET.SubElement(world, "light", name=light.name, directional=directional, pos=numbers(light.pos),
                      dir=numbers(light.dir))
    for geom in spec.worldbody.geoms:
        _geom(world, geom)
    for body in spec.worldbody.bodies:
        _body(world, body)
    if spec.equalities:
        equality = ET.SubElement(root, "equality")
        for weld in spec.equalities:
            if weld.type != mujoco.mjtEq.mjEQ_WELD:
                raise ValueError(f"scene equality {weld.name}: only welds are written (got {weld.type})")
            ET.SubElement(equality, "weld", name=weld.name, body1=weld.name1, body2=weld.name2,
                          anchor=numbers(weld.data[:WELD_RELPOSE]))
    return xml_text(root)


def scene_mjcf(bodies: Sequence[ObjectBody], background: Sequence[BackgroundGeom], up: np.ndarray,
               config: PhysicsConfig) -> str:
    """``scene.xml`` text (``scene_spec`` written by ``spec_xml``)."""
    return spec_xml(scene_spec(bodies, background, up, config))


def settle_scene(scene_xml: Path, seconds: float = 2.0) -> dict[str, float]:
    """Load ``scene.xml`` in MuJoCo, simulate ``seconds`` freely and return each object body's
    centre-of-mass displacement (m), by body name."""
    return {name: moved for name, (moved, _) in scene_motion(scene_xml, seconds).items()}


def scene_motion(scene_xml: Path, seconds: float) -> dict[str, tuple[float, float]]:
    """Load ``scene.xml`` in MuJoCo, simulate ``seconds`` freely: each object body's (centre-of-mass
    displacement in m, rotation in degrees), by body name."""
    model = mujoco.MjModel.from_xml_path(str(scene_xml))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    bodies = [b for b in range(1, model.nbody) if model.body(b).name.startswith(BODY_PREFIX)]
    start, turn = data.xipos[bodies].copy(), data.xquat[bodies].copy()
    mujoco.mj_step(model, data, nstep=int(round(seconds / model.opt.timestep)))
    moved = np.linalg.norm(data.xipos[bodies] - start, axis=1)
    dots = np.clip(np.abs(np.sum(data.xquat[bodies] * turn, axis=1)), 0.0, 1.0)
    return {model.body(b).name: (float(d), float(np.degrees(2 * np.arccos(c)))) for b, d, c in zip(bodies, moved, dots)}
