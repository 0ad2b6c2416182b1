"""``scene.usda`` (``layout.SCENE_USD``): the scene of ``scene.xml`` in OpenUSD, for Isaac Sim / Isaac Lab.

Written from the records ``scene.xml`` is written from, so an object's mass, centre of mass and
inertia exist once (``body.ObjectBody``, its ``MassProperties``) and the supports are the same
``supports.BackgroundGeom`` rows:

* stage: ``metersPerUnit`` 1, ``kilogramsPerUnit`` 1, ``upAxis`` Z (the world frame every output is
  written in, docs/architecture.md "Contracts"); ``/World/PhysicsScene`` with gravity −up × ``mjcf.GRAVITY``;
* ``/World/object_<id>``: an Xform at the pose's rotation and translation (the body frame of
  ``scene.xml``: canonical mesh frame, the pose's scale applied) with ``PhysicsRigidBodyAPI`` and
  ``PhysicsMassAPI`` (mass, centre of mass, principal moments and the rotation to their axes:
  ``MassProperties.principal``), bound to a physics material (friction, restitution);
  its ``visual`` child is the completed mesh, its ``collision/part_NN`` children the convex parts
  with ``PhysicsCollisionAPI`` and ``PhysicsMeshCollisionAPI`` (approximation ``convexHull``),
  purpose ``guide`` (colliders, not drawn); a mounted object's ``mount`` child is a
  ``PhysicsFixedJoint`` from the world (body0 unset) to it at its placement (``scene.xml``'s weld);
* ``/World/supports/<name>``: static colliders (a collision shape without a rigid body): a box as
  a ``Cube`` of size 2 scaled by its half sizes, a plane as a ``Plane`` (infinite in PhysX, as the
  MJCF plane is in MuJoCo), with the ground's material.

``pxr`` (PyPI ``usd-core``, the ``usd`` extra) is optional: ``write_scene_usd`` writes nothing
without it and returns the reason with how to get it.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from phirie_jax import layout
from phirie_jax.construct.physics.body import ObjectBody, body_name
from phirie_jax.construct.physics.mjcf import GRAVITY
from phirie_jax.construct.physics.priors import Priors
from phirie_jax.construct.physics.supports import BackgroundGeom
from phirie_jax.geometry import split_sim3
from phirie_jax.io.atomic import write_text
from phirie_jax.rotations import matrix_to_quat, quat_to_matrix

WORLD = "/World"
MOUNT_JOINT = "mount"     # a mounted object's fixed joint, a child of its body
MISSING_PXR = "pxr is not importable (install the usd extra: pip install 'phirie_jax[usd]', i.e. usd-core)"


def usd_available() -> bool:
    try:
        import pxr  # noqa: F401
    except ImportError:
        return False
    return True


def _quat(rotation: np.ndarray):
    """(3, 3) rotation → Gf.Quatd (w, x, y, z)."""
    from pxr import Gf

    w, x, y, z = matrix_to_quat(rotation)
    return Gf.Quatd(float(w), float(x), float(y), float(z))


def _place(xformable, translation=None, rotation=None, scale=None) -> None:
    """Translate, orient (double precision) and scale ops, in that order."""
    from pxr import Gf, UsdGeom

    if translation is not None:
        xformable.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*map(float, translation)))
    if rotation is not None:
        xformable.AddOrientOp(UsdGeom.XformOp.PrecisionDouble).Set(_quat(rotation))
    if scale is not None:
        xformable.AddScaleOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*map(float, scale)))


def _mesh(stage, path: str, vertices: np.ndarray, faces: np.ndarray):
    """A triangle ``UsdGeom.Mesh`` (vertices (V, 3), faces (F, 3)) with its extent."""
    from pxr import UsdGeom, Vt

    mesh = UsdGeom.Mesh.Define(stage, path)
    points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(vertices, np.float32))
    mesh.CreatePointsAttr(points)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(faces)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(faces, np.int32).ravel()))
    mesh.CreateExtentAttr(UsdGeom.PointBased.ComputeExtent(points))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    return mesh


def _material(stage, path: str, friction: float, restitution: float):
    """A physics material (static = dynamic friction, as MuJoCo has one sliding coefficient)."""
    from pxr import UsdPhysics, UsdShade

    material = UsdShade.Material.Define(stage, path)
    api = UsdPhysics.MaterialAPI.Apply(material.GetPrim())
    api.CreateStaticFrictionAttr(float(friction))
    api.CreateDynamicFrictionAttr(float(friction))
    api.CreateRestitutionAttr(float(restitution))
    return material


def _bind(prim, material) -> None:
    from pxr import UsdShade

    UsdShade.MaterialBindingAPI.Apply(prim).Bind(material, UsdShade.Tokens.weakerThanDescendants, "physics")


def _collider(prim, convex_hull: bool) -> None:
    from pxr import UsdPhysics

    UsdPhysics.CollisionAPI.Apply(prim)
    if convex_hull:
        UsdPhysics.MeshCollisionAPI.Apply(prim).CreateApproximationAttr(UsdPhysics.Tokens.convexHull)


def _body(stage, body: ObjectBody, visual: tuple[np.ndarray, np.ndarray] | None) -> None:
    """``/World/object_<id>``: rigid body, mass, material, visual mesh, convex parts."""
    from pxr import Gf, UsdGeom, UsdPhysics

    path = f"{WORLD}/{body_name(body.id)}"
    xform = UsdGeom.Xform.Define(stage, path)
    _, rotation, translation = split_sim3(body.pose)
    _place(xform, translation, rotation)
    prim = xform.GetPrim()
    UsdPhysics.RigidBodyAPI.Apply(prim)
    mass = UsdPhysics.MassAPI.Apply(prim)
    moments, axes = body.mass.principal()
    mass.CreateMassAttr(float(body.mass.mass))
    mass.CreateCenterOfMassAttr(Gf.Vec3f(*map(float, body.mass.com)))
    mass.CreateDiagonalInertiaAttr(Gf.Vec3f(*map(float, moments)))
    mass.CreatePrincipalAxesAttr(Gf.Quatf(_quat(axes)))
    _bind(prim, _material(stage, f"{path}/physics_material", body.priors.friction, body.priors.restitution))
    if visual is not None:
        _mesh(stage, f"{path}/visual", body.scale * np.asarray(visual[0], np.float64), visual[1])
    UsdGeom.Scope.Define(stage, f"{path}/collision")
    for k, part in enumerate(body.parts):  # already scaled: the body frame
        mesh = _mesh(stage, f"{path}/collision/part_{k:02d}", part.vertices, part.faces)
        mesh.CreatePurposeAttr(UsdGeom.Tokens.guide)
        _collider(mesh.GetPrim(), convex_hull=True)
    if body.mounted:   # the weld of scene.xml: fixed to the world where it is placed
        joint = UsdPhysics.FixedJoint.Define(stage, f"{path}/{MOUNT_JOINT}")
        joint.CreateBody1Rel().SetTargets([prim.GetPath()])
        joint.CreateLocalPos0Attr(Gf.Vec3f(*map(float, translation)))
        joint.CreateLocalRot0Attr(Gf.Quatf(_quat(rotation)))
        joint.CreateLocalPos1Attr(Gf.Vec3f(0.0, 0.0, 0.0))
        joint.CreateLocalRot1Attr(Gf.Quatf(1.0, 0.0, 0.0, 0.0))


def _support(stage, geom: BackgroundGeom, material) -> None:
    """A static collider for one support geom (scene frame, MuJoCo half sizes)."""
    from pxr import UsdGeom

    path = f"{WORLD}/supports/{geom.name}"
    rotation = quat_to_matrix(geom.quat)
    if geom.type == "box":
        shape = UsdGeom.Cube.Define(stage, path)
        shape.CreateSizeAttr(2.0)
        _place(shape, geom.pos, rotation, geom.size)
    elif geom.type == "plane":
        shape = UsdGeom.Plane.Define(stage, path)
        shape.CreateAxisAttr(UsdGeom.Tokens.z)
        shape.CreateWidthAttr(2.0 * float(geom.size[0]))
        shape.CreateLengthAttr(2.0 * float(geom.size[1]))
        _place(shape, geom.pos, rotation)
    else:
        raise ValueError(f"support geom {geom.name}: type {geom.type!r} has no USD collider (expected box or plane)")
    _collider(shape.GetPrim(), convex_hull=False)
    _bind(shape.GetPrim(), material)


def scene_usda(bodies: Sequence[ObjectBody], visuals: Sequence[tuple[np.ndarray, np.ndarray] | None],
               background: Sequence[BackgroundGeom], up: np.ndarray, ground: Priors) -> str:
    """The ``.usda`` text of the scene.

    Args:
        bodies: the objects of ``scene.xml`` (their parts in the body frame, scale applied).
        visuals: per body, its completed mesh (vertices (V, 3), faces (F, 3)) in the canonical
            frame, unscaled, or None.
        background: the support geoms (scene frame).
        up: (3,) the scene's up; gravity is −up.
        ground: the supports' contact priors (friction, restitution).
    """
    from pxr import Gf, Usd, UsdGeom, UsdPhysics

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdPhysics.SetStageKilogramsPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, WORLD)
    stage.SetDefaultPrim(world.GetPrim())
    scene = UsdPhysics.Scene.Define(stage, f"{WORLD}/PhysicsScene")
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    scene.CreateGravityDirectionAttr(Gf.Vec3f(*map(float, -up + 0.0)))  # no "-0"
    scene.CreateGravityMagnitudeAttr(GRAVITY)
    for body, visual in zip(bodies, visuals, strict=True):
        _body(stage, body, visual)
    if background:
        UsdGeom.Scope.Define(stage, f"{WORLD}/supports")
        material = _material(stage, f"{WORLD}/supports/physics_material", ground.friction, ground.restitution)
        for geom in background:
            _support(stage, geom, material)
    return stage.GetRootLayer().ExportToString()


def write_scene_usd(out_dir: Path, bodies: Sequence[ObjectBody],
                    visuals: Sequence[tuple[np.ndarray, np.ndarray] | None], background: Sequence[BackgroundGeom],
                    up: np.ndarray, ground: Priors) -> dict:
    """Write ``scene.usda`` (atomically) when ``pxr`` is importable; returns the manifest's record:
    ``{"path": "scene.usda"}``, or ``{"path": None, "reason": ...}`` saying how to get it."""
    path = Path(out_dir) / layout.SCENE_USD
    if not usd_available():
        path.unlink(missing_ok=True)  # an earlier run's file would no longer match scene.xml
        return {"path": None, "reason": MISSING_PXR}
    write_text(path, scene_usda(bodies, visuals, background, up, ground))
    return {"path": layout.SCENE_USD}
