"""The physics stage: ``run_physics(scene_dir, out_dir, config)`` and ``run_droptest(out_dir, config)``.

For every accepted object of the manifest (written by the object-construction stage):
repair its canonical mesh, decompose it with CoACD (hull fallback recorded), write the parts
to ``objects/<id>/collision/part_NN.obj`` (canonical frame), set the physics priors and the
uniform-density inertia, write ``objects/<id>/object.urdf``. A mesh that cannot be a rigid
body (empty, non-manifold, zero volume, MuJoCo refuses it) makes that object "failed" with
the reason; the others go on. Then the supports are fitted, ``scene.xml`` is written and
loaded back, all objects are drop-tested in one batch (``run_droptest``, which also re-runs
on an exported folder alone), and a 2 s free settle of the whole scene is recorded.

Manifest: each object gets ``collision``, ``mass``, ``friction``, ``physics`` (priors, mass
properties, collision report, URDF path, body name), ``drop_test`` and its ``checks.settling``
row; the ``physics`` section holds the scene, background geoms, settle and config; timings
``physics`` and ``physics.<step>``.
"""

from __future__ import annotations

import dataclasses
import time
import traceback
from pathlib import Path

import numpy as np

from phirie_jax.construct.physics import droptest as dt
from phirie_jax.construct.physics.collision import MeshError, collision_from_mesh
from phirie_jax.construct.physics.config import PhysicsConfig
from phirie_jax.construct.physics.export import (
    SceneObject,
    body_name,
    read_part,
    scene_mjcf,
    settle_scene,
    write_parts,
    write_urdf,
)
from phirie_jax.construct.physics.priors import Priors, mass_properties, priors
from phirie_jax.construct.physics.supports import PlacedBody, fit_background
from phirie_jax.geometry import split_sim3
from phirie_jax.io.atomic import write_text
from phirie_jax.manifest import Manifest, to_dict

SCENE_FILE = "scene.xml"
SETTLE_SECONDS = 2.0


def _path(out_dir: Path, p: str) -> Path:
    return Path(p) if Path(p).is_absolute() else out_dir / p


def _up(manifest: Manifest) -> np.ndarray:
    up = ((manifest.get("construct") or {}).get("gravity") or {}).get("up")
    return np.asarray(up if up is not None else (0.0, 0.0, 1.0), np.float64)


def _load_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    if not path.is_file():
        raise MeshError(f"mesh file missing: {path}")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as err:  # noqa: BLE001 — any reader failure is this object's failure
        raise MeshError(f"mesh file unreadable: {path}: {err}") from None
    if not hasattr(mesh, "faces"):
        raise MeshError(f"mesh file holds no triangles: {path}")
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def _categories(manifest: Manifest) -> dict:
    return {inst["id"]: inst.get("category") for inst in manifest.get("instances") or []}


def build_object(entry: dict, category: str | None, out_dir: Path, config: PhysicsConfig) -> dict:
    """Collision, priors, inertia and URDF of one accepted object → the fields to update."""
    if entry.get("pose") is None or not entry.get("mesh"):
        raise MeshError("accepted object without a pose or mesh in the manifest")
    scale, _, _ = split_sim3(np.asarray(entry["pose"]))
    vertices, faces = _load_mesh(_path(out_dir, entry["mesh"]))
    collision = collision_from_mesh(vertices, faces, config)
    pr = priors(category, config)
    paths = write_parts(out_dir, entry["id"], collision.parts)
    # mass properties of the parts as written, so URDF, MJCF and the drop test agree to the digit
    parts = tuple(read_part(out_dir / p) for p in paths)
    scaled = tuple(dataclasses.replace(p, vertices=scale * p.vertices) for p in parts)
    mass = mass_properties(scaled, pr.mass)
    # MuJoCo must accept the body on its own before it goes into the scene
    dt.build_model(dt.DropBody(scaled, mass, np.eye(3), pr), dt.part_bucket(len(scaled), config.drop_test),
                   config.drop_test)
    urdf = write_urdf(out_dir, entry["id"], entry.get("mesh"), paths, scale, mass, pr)
    return {"collision": paths, "mass": pr.mass, "friction": pr.friction,
            "physics": {"body": body_name(entry["id"]), "urdf": urdf, "scale": scale, "priors": pr.record(),
                        "mass_properties": mass.record(), "collision": collision.report}}


def _build_outcome(entry: dict, category: str | None, out_dir: Path, config: PhysicsConfig) -> dict:
    """``{"update": ...}`` of ``build_object``, or ``{"reason": ..., ["traceback": ...]}``."""
    try:
        return {"update": build_object(entry, category, out_dir, config)}
    except (MeshError, ValueError, OSError) as err:
        return {"reason": str(err)}
    except Exception as err:  # noqa: BLE001 — one object's failure is recorded, the scene goes on
        return {"reason": f"{type(err).__name__}: {err}", "traceback": traceback.format_exc(limit=4)}


def build_objects(entries: list[dict], categories: dict, out_dir: Path, config: PhysicsConfig) -> list[dict]:
    """``_build_outcome`` of every entry, in ``config.workers`` processes (CoACD is single-threaded).

    A worker that dies (CoACD crashing in native code) takes only its object down: the objects
    it left unfinished are retried alone, and the one that kills its process again is recorded.
    """
    import multiprocessing
    import os
    from concurrent.futures import ProcessPoolExecutor
    from concurrent.futures.process import BrokenProcessPool

    args = [(e, categories.get(e["id"]), out_dir, config) for e in entries]
    workers = min(len(args), config.workers or os.cpu_count() or 1)
    if workers <= 1:
        return [_build_outcome(*a) for a in args]
    spawn = multiprocessing.get_context("spawn")  # never fork a process that holds JAX threads
    outcomes: list[dict | None] = [None] * len(args)
    with ProcessPoolExecutor(workers, mp_context=spawn) as pool:
        futures = [pool.submit(_build_outcome, *a) for a in args]
        for k, future in enumerate(futures):
            try:
                outcomes[k] = future.result()
            except BrokenProcessPool:
                pass
    for k, outcome in enumerate(outcomes):
        if outcome is None:
            with ProcessPoolExecutor(1, mp_context=spawn) as alone:
                try:
                    outcomes[k] = alone.submit(_build_outcome, *args[k]).result()
                except BrokenProcessPool:
                    outcomes[k] = {"reason": "the collision process died (CoACD crashed on this mesh)"}
    return outcomes


def _drop_body(entry: dict, out_dir: Path, up: np.ndarray) -> tuple[dt.DropBody, SceneObject]:
    """The drop body and scene object of an exported object, read back from its files."""
    parts = tuple(read_part(_path(out_dir, p)) for p in entry["collision"])
    phys = entry["physics"]
    pr = Priors(**{**phys["priors"], "solref": tuple(phys["priors"]["solref"]),
                   "solimp": tuple(phys["priors"]["solimp"])})
    pr = dataclasses.replace(pr, mass=float(entry.get("mass", pr.mass)), friction=float(entry.get("friction",
                                                                                                  pr.friction)))
    body = dt.body_from_parts(parts, np.asarray(entry["pose"]), up, pr)
    return body, SceneObject(entry["id"], tuple(entry["collision"]), np.asarray(entry["pose"]), body.mass, pr)


def _fail(entry: dict, reason: str, **extra) -> None:
    entry.update(status="failed", reason=f"physics: {reason}", **extra)


def run_droptest(out_dir: str | Path, config: PhysicsConfig | None = None, manifest: Manifest | None = None) -> dict:
    """Drop-test every exported object (collision parts read from their files) in one batch;
    writes ``drop_test`` and ``checks.settling`` of each and returns the manifest."""
    out_dir = Path(out_dir)
    config = config or PhysicsConfig()
    manifest = manifest or Manifest.load_or_create(out_dir)
    objects = manifest.require("objects", "the object and physics stages")
    start = time.perf_counter()
    up = _up(manifest)
    entries, bodies = [], []
    for entry in objects:
        if entry.get("status") != "accepted" or not entry.get("collision") or not entry.get("physics"):
            continue
        try:
            body, _ = _drop_body(entry, out_dir, up)
        except (OSError, ValueError, KeyError, TypeError) as err:
            entry["drop_test"] = dt.DropResult(None, None, None, None, None,
                                               dt.resolve_backend(config.drop_test.backend),
                                               f"exported files unreadable: {err}").record()
            continue
        entries.append(entry)
        bodies.append(body)
    results = dt.drop_test(bodies, config.drop_test)
    method = f"drop test of the exported collision parts ({dt.resolve_backend(config.drop_test.backend)})"
    for entry, result in zip(entries, results):
        entry["drop_test"] = result.record()
        entry.setdefault("checks", {})["settling"] = dt.settling_check(result, config.drop_test, method)
        if "unresolved_checks" in entry:
            bad = [n for n in entry["unresolved_checks"] if n != "settling"]
            entry["unresolved_checks"] = bad + (["settling"] if result.stable is False else [])
    manifest.set("objects", objects)
    manifest.record_timing("droptest", time.perf_counter() - start)
    manifest.write()
    return manifest.data


def run_physics(scene_dir: str | Path | None, out_dir: str | Path, config: PhysicsConfig | None = None) -> dict:
    """The physics stage (module docstring). ``scene_dir`` is unused beyond the manifest's paths."""
    del scene_dir  # the manifest holds every path this stage needs (mesh, surface)
    out_dir = Path(out_dir)
    config = config or PhysicsConfig()
    manifest = Manifest.load_or_create(out_dir)
    objects = manifest.require("objects", "the object-construction stage")
    start = time.perf_counter()
    up, categories = _up(manifest), _categories(manifest)
    t0 = time.perf_counter()
    accepted = [e for e in objects if e.get("status") == "accepted"]
    for entry, outcome in zip(accepted, build_objects(accepted, categories, out_dir, config)):
        if "update" in outcome:
            entry.update(outcome["update"])
        else:
            _fail(entry, outcome["reason"], collision=[],
                  **({"traceback": outcome["traceback"]} if "traceback" in outcome else {}))
    manifest.record_timing("physics.collision", time.perf_counter() - t0)
    t0 = time.perf_counter()
    scene_objects, placed = [], []
    for entry in objects:
        if entry.get("status") == "accepted" and entry.get("collision"):
            body, obj = _drop_body(entry, out_dir, up)
            scene_objects.append(obj)
            scale, rot, trans = split_sim3(obj.pose)
            pts = np.concatenate([(scale * p.vertices) @ rot.T + trans for p in body.parts])
            support = (entry.get("support") or {}).get("height")
            placed.append(PlacedBody(entry["id"], pts, None if support is None else float(support)))
    surface = _surface(manifest, out_dir)
    background = fit_background(placed, up, surface, config.support_thickness, config.background)
    write_text(out_dir / SCENE_FILE, scene_mjcf(scene_objects, background, up, config))
    settle = settle_scene(out_dir / SCENE_FILE, SETTLE_SECONDS)   # also proves that it loads
    manifest.record_timing("physics.export", time.perf_counter() - t0)
    manifest.set("objects", objects)
    t0 = time.perf_counter()
    run_droptest(out_dir, config, manifest)
    manifest.record_timing("physics.droptest", time.perf_counter() - t0)
    manifest.set("physics", {"scene": SCENE_FILE, "up": up, "background": [g.record() for g in background],
                             "surface": None if surface is None else surface.metadata.get("phirie_path"),
                             "scene_settle": {"seconds": SETTLE_SECONDS, "displacement_m": settle},
                             "config": to_dict(config)})
    manifest.record_timing("physics", time.perf_counter() - start)
    manifest.write()
    return manifest.data


def _surface(manifest: Manifest, out_dir: Path):
    """The scene surface the earlier stages used (trimesh), or None."""
    import trimesh

    candidates = [(manifest.get("construct") or {}).get("surface"),
                  ((manifest.get("observe") or {}).get("surface") or {}).get("path")]
    for p in candidates:
        if p and _path(out_dir, p).is_file():
            try:
                mesh = trimesh.load(_path(out_dir, p), force="mesh", process=False)
                mesh.metadata["phirie_path"] = str(p)
                return mesh
            except Exception:  # noqa: BLE001 — no surface: the supports fall back to the footprints
                continue
    return None


def summary(manifest: dict) -> list[dict]:
    """Per object: id, status, parts, mass, drop-test verdict (for the CLI's table)."""
    rows = []
    for o in manifest.get("objects", []):
        drop = o.get("drop_test") or {}
        rows.append({"id": o["id"], "status": o["status"], "parts": len(o.get("collision") or []),
                     "mass": o.get("mass"), "stable": drop.get("stable"), "drift_m": drop.get("drift_m"),
                     "reason": o.get("reason") or drop.get("error")})
    return rows
