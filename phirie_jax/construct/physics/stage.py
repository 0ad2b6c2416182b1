"""The physics stage: ``physics(objects, categories, up, surfaces, out_dir, config)`` and
``drop_test_objects(objects, up, out_dir, config)`` (``run_physics`` and ``run_droptest`` on an
output folder alone).

For every kept object (``records.ObjectRecord``, from the object-construction stage):
repair its canonical mesh, decompose it with CoACD (hull fallback recorded), write the parts
to ``objects/<id>/collision/part_NN.obj`` (canonical frame), set the physics priors and the
uniform-density inertia (its ``body.ObjectBody``), write ``objects/<id>/object.urdf``. A mesh
that cannot be a rigid body (empty, non-manifold, zero volume, MuJoCo refuses it) makes that
object "failed" with the reason; the others go on. Then the supports are fitted, ``scene.xml``
(and ``scene.usda`` from the same records, when ``pxr`` is importable) is written and loaded
back, all objects are drop-tested in one batch (``run_droptest``, which also re-runs on an
exported folder alone; a mounted object, welded to its wall, gets the hold test of the
exported scene instead), and a 2 s free settle of the whole scene is recorded.

Manifest: each object gets ``collision``, ``mass``, ``friction``, ``physics`` (priors, mass
properties, collision report, URDF path, body name), ``drop_test`` and its ``checks.settling``
row; the ``physics`` section holds the scene, its USD record, background geoms, settle, the
collision's worker processes, their OpenMP threads and niceness (``collision_workers``) and
config; timings ``physics`` and ``physics.<step>``.
"""

from __future__ import annotations

import dataclasses
import time
import traceback
from pathlib import Path

import numpy as np

from phirie_jax import layout
from phirie_jax.construct.objects.checks import kept_reason
from phirie_jax.construct.physics import droptest
from phirie_jax.construct.physics.body import ObjectBody, body_name, object_body
from phirie_jax.construct.physics.collision import MeshError, collision_from_mesh
from phirie_jax.construct.physics.config import PhysicsConfig
from phirie_jax.construct.physics.mjcf import scene_mjcf, settle_scene
from phirie_jax.construct.physics.parts import read_part, write_parts
from phirie_jax.construct.physics.priors import Priors, Shape, priors
from phirie_jax.construct.physics.supports import PlacedBody, fit_background
from phirie_jax.construct.physics.urdf import write_urdf
from phirie_jax.construct.physics.usd import write_scene_usd
from phirie_jax.errors import SceneInputError
from phirie_jax.geometry import split_sim3
from phirie_jax.io.atomic import write_text
from phirie_jax.io.mesh import load_trimesh, read_mesh
from phirie_jax.manifest import ACCEPTED, FAILED_OBJECT, UNVERIFIED, Manifest, Timings, to_dict
from phirie_jax.native import IsolatedPool
from phirie_jax.progress import task
from phirie_jax.records import Check, ObjectRecord, PhysicsRecord, plain

SETTLE_SECONDS = 2.0


# --- the stage -------------------------------------------------------------------------


def run_physics(scene_dir: str | Path | None, out_dir: str | Path, config: PhysicsConfig | None = None,
                collision: CollisionJob | None = None) -> dict:
    """The physics stage on an output folder alone (``physics``; the folder's manifest read and
    written). ``scene_dir`` is unused: the manifest holds every path this stage needs."""
    del scene_dir
    manifest = Manifest.load_or_create(out_dir)
    objects = manifest.require("objects", "the object-construction stage")
    objects, section = physics(objects, manifest.categories(), manifest.up(), manifest.surface_paths(), out_dir,
                               config, collision, manifest.timings)
    manifest.set("objects", objects)
    manifest.set("physics", section)
    manifest.write()
    return manifest.data


def physics(objects: tuple[ObjectRecord, ...], categories: dict, up: np.ndarray, surface_paths: list[str],
            out_dir: str | Path, config: PhysicsConfig | None = None, collision: CollisionJob | None = None,
            timings: Timings | None = None) -> tuple[tuple[ObjectRecord, ...], PhysicsRecord]:
    """The physics stage (module docstring) of the objects (``categories``: instance id →
    category; ``up``: (3,) the scene's; ``surface_paths``: the scene surfaces the earlier stages
    recorded) → (the objects with their bodies and drop tests, the ``physics`` record).
    collision: the objects' collision already started (``start_collision``), whose outcomes are
    taken instead of building them here; timings ``physics.collision`` (its own wall time) and
    ``physics.collision_wait`` (what this stage still waited for it)."""
    out_dir = Path(out_dir)
    config = config or PhysicsConfig()
    timings = timings if timings is not None else Timings()
    with timings.timed("physics"):
        if collision is None:
            with timings.timed("physics.collision"):
                objects = build_accepted(objects, categories, out_dir, config)
            pool = pool_record(sum(e.kept for e in objects), config)
        else:
            with timings.timed("physics.collision_wait"):
                objects = apply_outcomes(objects, collision.ids, collision.outcomes())
            timings.record("physics.collision", collision.seconds)
            pool = pool_record(len(collision.ids), config)
        with timings.timed("physics.export"):
            section = export_scene(objects, up, _surface(surface_paths, out_dir), out_dir, config)
        section["collision_workers"] = pool
        with timings.timed("physics.droptest"):
            objects = drop_test_objects(objects, up, out_dir, config, timings)
    return objects, PhysicsRecord.from_json(plain(section))


def run_droptest(out_dir: str | Path, config: PhysicsConfig | None = None) -> dict:
    """The drop tests on an exported folder alone (``drop_test_objects``): the objects and physics
    stages must have completed (``SceneInputError`` naming the one that did not). Returns the
    manifest."""
    manifest = Manifest.load(out_dir)
    manifest.require_complete(("objects", "physics"), "the drop tests")
    objects = manifest.require("objects", "the object and physics stages")
    manifest.set("objects", drop_test_objects(objects, manifest.up(), out_dir, config, manifest.timings))
    manifest.write()
    return manifest.data


def drop_test_objects(objects: tuple[ObjectRecord, ...], up: np.ndarray, out_dir: str | Path,
                      config: PhysicsConfig | None = None, timings: Timings | None = None
                      ) -> tuple[ObjectRecord, ...]:
    """Drop-test every exported object (collision parts read from their files) in one batch →
    the objects with their ``drop_test`` and ``checks.settling`` (timing ``droptest``)."""
    config = config or PhysicsConfig()
    timings = timings if timings is not None else Timings()
    with timings.timed("droptest"):
        objects, tested, bodies = exported_bodies(objects, Path(out_dir), up, config)
        dropped = [(k, b) for k, b in zip(tested, bodies) if not b.body.mounted]
        held = [k for k, b in zip(tested, bodies) if b.body.mounted]
        results = dict(zip([k for k, _ in dropped], droptest.drop_test([b for _, b in dropped], config.drop_test)))
        if held:
            welded = droptest.hold_test(Path(out_dir) / layout.SCENE_MJCF, [body_name(objects[k].id) for k in held],
                                        config.drop_test)
            results.update({k: welded[body_name(objects[k].id)] for k in held})
        verdicts = record_verdicts([objects[k] for k in tested], [results[k] for k in tested], config)
        done = dict(zip(tested, verdicts))
    return tuple(done.get(k, o) for k, o in enumerate(objects))


# --- step 1: collision, priors, inertia, URDF of each accepted object -------------------


def build_accepted(objects: tuple[ObjectRecord, ...], categories: dict, out_dir: Path, config: PhysicsConfig
                   ) -> tuple[ObjectRecord, ...]:
    """Every kept object built: its fields on success, else status "failed" with the reason."""
    accepted = [e for e in objects if e.kept]
    return apply_outcomes(objects, [e.id for e in accepted], build_objects(accepted, categories, out_dir, config))


def apply_outcomes(objects: tuple[ObjectRecord, ...], ids: list, outcomes: list[dict]) -> tuple[ObjectRecord, ...]:
    """The objects with each outcome of ``_build_outcome`` applied to the object of its id."""
    by_id = dict(zip(ids, outcomes))

    def applied(entry: ObjectRecord) -> ObjectRecord:
        outcome = by_id.get(entry.id)
        if outcome is None:
            return entry
        if "update" in outcome:
            return entry.with_fields(**outcome["update"])
        return _fail(entry, outcome["reason"], collision=(),
                     **({"traceback": outcome["traceback"]} if "traceback" in outcome else {}))

    return tuple(applied(e) for e in objects)


def build_object(entry: ObjectRecord, category: str | None, out_dir: Path, config: PhysicsConfig) -> dict:
    """Collision, priors, inertia and URDF of one accepted object → the fields to update."""
    if entry.pose is None or not entry.mesh:
        raise MeshError("accepted object without a pose or mesh in the manifest")
    pose = np.asarray(entry.pose)
    split_sim3(pose)   # a pose that is no similarity fails before the mesh work
    vertices, faces = _load_mesh(layout.resolve(out_dir, entry.mesh))
    collision = collision_from_mesh(vertices, faces, config)
    paths = write_parts(out_dir, entry.id, collision.parts)
    shape = Shape.of_mesh(vertices, faces, split_sim3(pose)[0])
    # the parts as written, so URDF, MJCF and the drop test agree to the digit
    body = object_body(entry.id, [read_part(out_dir / p) for p in paths], pose,
                       priors(category, config, shape, entry.id), paths)
    # MuJoCo must accept the body on its own before it goes into the scene
    droptest.build_model(droptest.DropBody(body, np.eye(3)), droptest.part_bucket(len(body.parts), config.drop_test),
                         config.drop_test)
    urdf = write_urdf(out_dir, body, entry.mesh)
    pr = body.priors
    return {"collision": tuple(paths), "mass": pr.mass, "friction": pr.friction,
            "physics": {"body": body_name(entry.id), "urdf": urdf, "scale": body.scale, "priors": pr.record(),
                        "mass_properties": body.mass.record(), "collision": collision.report}}


def _build_outcome(entry: ObjectRecord, category: str | None, out_dir: Path, config: PhysicsConfig) -> dict:
    """``{"update": ...}`` of ``build_object``, or ``{"reason": ..., ["traceback": ...]}``."""
    try:
        return {"update": build_object(entry, category, out_dir, config)}
    except (MeshError, ValueError, OSError) as err:
        return {"reason": str(err)}
    except Exception as err:  # noqa: BLE001 — one object's failure is recorded, the scene goes on
        return {"reason": f"{type(err).__name__}: {err}", "traceback": traceback.format_exc(limit=4)}


def build_objects(entries: list[ObjectRecord], categories: dict, out_dir: Path, config: PhysicsConfig,
                  build=None) -> list[dict]:
    """``_build_outcome`` of every entry, at most ``config.workers`` at once, each in its own
    fresh interpreter (``native.IsolatedPool``; each with its OpenMP team, ``worker_threads``).

    A build whose process dies (CoACD crashing in native code) is that object's recorded
    failure; the others go on. A single object, or a single core, still builds in a child
    process; only ``workers=1`` builds in this one (unprotected: for debugging). ``build``: what
    runs per entry (a top-level function; default ``_build_outcome``). The children never
    outlive this process (``native.die_with_parent``), and a Ctrl-C kills them at once.
    """
    with CollisionJob(entries, categories, out_dir, config, build) as job:   # Ctrl-C at any point: terminated
        return job.outcomes()


def _advanced(outcome: dict, advance) -> dict:
    advance()
    return outcome


def _worker_count(objects: int, config: PhysicsConfig) -> int:
    import os

    return max(1, min(objects, config.workers or os.cpu_count() or 1))


CRASHED = "the collision process died (CoACD crashed on this mesh: {})"


def _gathered(futures: list, advance) -> list[dict]:
    """Each future's outcome in order; a build whose process died (CoACD crashing in native
    code) is that object's recorded failure."""
    from phirie_jax.errors import NativeLibraryError

    outcomes = []
    for future in futures:
        try:
            outcome = future.result()
        except NativeLibraryError as err:
            outcome = {"reason": CRASHED.format(err.signal or "no result")}
        outcomes.append(_advanced(outcome, advance))
    return outcomes


def longest_first(entries: list[ObjectRecord], out_dir: Path) -> list[int]:
    """The order in which to start the entries' collision: the largest mesh files first (ties in
    order), so that the slowest decompositions (concave visual hulls: the most triangles, and
    minutes of CoACD where a box takes a second) do not start last behind the quick ones."""
    def size(k: int) -> int:
        try:
            return layout.resolve(out_dir, entries[k].mesh).stat().st_size if entries[k].mesh else 0
        except (OSError, ValueError):
            return 0

    return sorted(range(len(entries)), key=lambda k: -size(k))


class CollisionJob:
    """The accepted objects' collision, built in worker processes from ``start_collision`` on, so
    the caller can use the accelerator meanwhile (the background stage needs only the objects'
    meshes); ``outcomes()`` waits for it. A ``with`` block around the work done meanwhile
    terminates the workers when that work raises. With ``workers=1`` it builds in ``outcomes()``.
    ``build``: what runs per entry (``build_objects``)."""

    def __init__(self, entries: list[ObjectRecord], categories: dict, out_dir: Path, config: PhysicsConfig,
                 build=None):
        self.ids = [e.id for e in entries]
        self._build = _build_outcome if build is None else build
        self._args = [(e, categories.get(e.id), out_dir, config) for e in entries]
        self._start = time.perf_counter()
        self._finished = self._start
        self._pool = self._futures = None
        if config.workers != 1 and self._args:
            workers = _worker_count(len(self._args), config)
            self._pool = IsolatedPool("CoACD", workers, worker_threads(workers, config), config.coacd.niceness)
            futures = {}
            try:
                for k in longest_first(entries, out_dir):
                    a = self._args[k]
                    futures[k] = self._pool.submit(self._build, *a, description=f"collision of object {a[0].id}")
                    futures[k].add_done_callback(self._note_finish)
                self._futures = [futures[k] for k in range(len(self._args))]
            except BaseException:   # Ctrl-C while submitting: no worker is left building
                self.cancel()
                raise
        self.seconds = 0.0   # the collision's own wall time, once ``outcomes()`` returned

    def _note_finish(self, _future) -> None:
        self._finished = max(self._finished, time.perf_counter())

    def __enter__(self) -> CollisionJob:
        return self

    def __exit__(self, kind, err, trace) -> None:
        if kind is not None:
            self.cancel()

    def cancel(self) -> None:
        """Terminate the workers now (what they were building is dropped)."""
        if self._pool is not None:
            self._pool.terminate()
            self._pool = None

    def outcomes(self) -> list[dict]:
        """``build`` of every entry, in order (waits for the workers)."""
        with task("collision (CoACD per object)", len(self._args)) as advance:
            if self._futures is None:
                outcomes = [_advanced(self._build(*a), advance) for a in self._args]
                self._finished = time.perf_counter()
            else:
                with self._pool:   # an exception here (Ctrl-C) terminates the workers at once
                    outcomes = _gathered(self._futures, advance)
                self._pool = None
        self.seconds = self._finished - self._start
        return outcomes


def start_collision(objects: tuple[ObjectRecord, ...], categories: dict, out_dir: str | Path,
                    config: PhysicsConfig | None = None) -> CollisionJob:
    """Start building the collision of the kept objects (``CollisionJob``; ``categories``:
    instance id → category)."""
    return CollisionJob([e for e in objects if e.kept], categories, Path(out_dir), config or PhysicsConfig())


def pool_record(objects: int, config: PhysicsConfig) -> dict:
    """The manifest's record of how ``objects`` objects' collision was built: worker processes (0:
    in the stage's own process), the OpenMP threads of each and how much lower their priority is."""
    if config.workers == 1 or objects == 0:
        return {"workers": 0, "omp_threads": None, "niceness": None}
    workers = _worker_count(objects, config)
    return {"workers": workers, "omp_threads": worker_threads(workers, config), "niceness": config.coacd.niceness}


# Each collision worker's OpenMP team, as a multiple of its share of the cores: the concave objects
# outlast the quick ones, and their teams then take the cores those left (``CoacdConfig.threads``).
OPENMP_OVERSUBSCRIPTION = 2


def worker_threads(workers: int, config: PhysicsConfig) -> int:
    """OpenMP threads of each collision worker: ``config.coacd.threads``, or
    ``OPENMP_OVERSUBSCRIPTION`` times the CPU cores shared among ``workers``, at least one and at
    most the cores (a lone worker has no cores left to take)."""
    import os

    cores = os.cpu_count() or 1
    return config.coacd.threads or max(1, min(cores, OPENMP_OVERSUBSCRIPTION * cores // max(1, workers)))


# --- step 2: supports, scene.xml and its free settle -----------------------------------


def export_scene(objects: tuple[ObjectRecord, ...], up: np.ndarray, surface, out_dir: Path, config: PhysicsConfig) -> dict:
    """Fit the supports, write ``scene.xml`` and settle it (which also proves that it loads);
    returns the manifest's ``physics`` section. ``surface``: the scene surface (trimesh) or None."""
    exported = [e for e in objects if e.kept and e.collision]
    bodies = [exported_body(e, out_dir) for e in exported]
    placed = [_placed(body, e) for body, e in zip(bodies, exported)]
    background = fit_background(placed, up, surface, config.support_thickness, config.background)
    write_text(out_dir / layout.SCENE_MJCF, scene_mjcf(bodies, background, up, config))
    usd = write_scene_usd(out_dir, bodies, [_visual_mesh(e, out_dir) for e in exported], background, up,
                          priors(None, config))
    settle = settle_scene(out_dir / layout.SCENE_MJCF, SETTLE_SECONDS)
    return {"scene": layout.SCENE_MJCF, "usd": usd, "up": up, "background": [g.record() for g in background],
            "surface": None if surface is None else surface.metadata.get("phirie_path"),
            "scene_settle": {"seconds": SETTLE_SECONDS, "displacement_m": settle}, "config": to_dict(config)}


def _visual_mesh(entry: ObjectRecord, out_dir: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """The completed mesh of an exported object (canonical frame), for ``scene.usda``'s visual."""
    try:
        return _load_mesh(layout.resolve(out_dir, entry.mesh)) if entry.mesh else None
    except MeshError:
        return None


def _placed(body: ObjectBody, entry: ObjectRecord) -> PlacedBody:
    """The body's collision vertices placed in the scene, with its support height when known."""
    _, rot, trans = split_sim3(body.pose)  # the parts already carry the pose's scale
    pts = np.concatenate([p.vertices @ rot.T + trans for p in body.parts])
    return PlacedBody(entry.id, pts, entry.support_height)


# --- step 3: drop tests of the exported files ------------------------------------------


def exported_bodies(objects: tuple[ObjectRecord, ...], out_dir: Path, up: np.ndarray, config: PhysicsConfig
                    ) -> tuple[tuple[ObjectRecord, ...], list[int], list[droptest.DropBody]]:
    """(the objects, an object whose files cannot be read with its ``drop_test`` error; the
    positions of the exported objects that can be tested; their drop bodies)."""
    objects, tested, bodies = list(objects), [], []
    for k, entry in enumerate(objects):
        if not entry.kept or not entry.collision or not entry.physics:
            continue
        try:
            bodies.append(droptest.drop_body(exported_body(entry, out_dir), up))
        except (OSError, ValueError, KeyError, TypeError) as err:
            objects[k] = dataclasses.replace(entry, drop_test=droptest.DropResult.not_run(
                droptest.resolve_backend(config.drop_test.backend), f"exported files unreadable: {err}").record())
            continue
        tested.append(k)
    return tuple(objects), tested, bodies


def record_verdicts(entries: list[ObjectRecord], results: list[droptest.DropResult], config: PhysicsConfig
                    ) -> list[ObjectRecord]:
    """Each object with its ``drop_test``, ``checks.settling`` and ``unresolved_checks`` from its
    result (a kept object's status follows its unresolved checks)."""
    backend = droptest.resolve_backend(config.drop_test.backend, len(entries))
    dropped = f"drop test of the exported collision parts ({backend})"
    held = f"hold test: mounted, welded to its wall in the exported scene ({droptest.HOLD_BACKEND})"
    out = []
    for entry, result in zip(entries, results):
        method = held if entry.mounted else dropped
        settling = Check.from_json("settling", droptest.settling_check(result, config.drop_test, method))
        checks = tuple(settling if c.name == "settling" else c for c in entry.checks)
        entry = dataclasses.replace(entry, drop_test=result.record(),
                                    checks=checks if entry.check("settling") else (*checks, settling))
        if entry.unresolved_checks is not None:
            bad = [n for n in entry.unresolved_checks if n != "settling"] + (["settling"] if result.stable is False
                                                                               else [])
            entry = entry.with_fields(unresolved_checks=bad)
            if entry.kept:
                gap = (entry.extra.get("support") or {}).get("gap_m")
                entry = entry.with_fields(status=UNVERIFIED if bad else ACCEPTED,
                                          reason=kept_reason(bad, gap, config.drop_test.max_drift, entry.mounted))
        out.append(entry)
    return out


# --- reading the manifest and the files ------------------------------------------------


def exported_body(entry: ObjectRecord, out_dir: Path) -> ObjectBody:
    """The body of an exported object, read back from its part files and its manifest priors
    (the manifest's ``mass`` and ``friction`` win over the recorded priors)."""
    parts = [read_part(layout.resolve(out_dir, p)) for p in entry.collision]
    recorded = entry.physics["priors"]
    pr = Priors(**{**recorded, "solref": tuple(recorded["solref"]), "solimp": tuple(recorded["solimp"])})
    pr = dataclasses.replace(pr, mass=float(pr.mass if entry.mass is None else entry.mass),
                             friction=float(pr.friction if entry.friction is None else entry.friction))
    return object_body(entry.id, parts, np.asarray(entry.pose), pr, list(entry.collision), entry.mounted)


def _load_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3), faces (F, 3)) of an object's mesh; a missing or unreadable file is a
    ``MeshError`` (that object fails, not the stage)."""
    try:
        return read_mesh(path)
    except SceneInputError as err:
        raise MeshError(str(err)) from None


def _fail(entry: ObjectRecord, reason: str, **extra) -> ObjectRecord:
    return entry.with_fields(status=FAILED_OBJECT, reason=f"physics: {reason}", **extra)


def _surface(surface_paths: list[str], out_dir: Path):
    """The scene surface the earlier stages used (trimesh), or None."""
    for p in surface_paths:
        if p and layout.resolve(out_dir, p).is_file():
            try:
                mesh = load_trimesh(layout.resolve(out_dir, p))
            except SceneInputError:  # no surface: the supports fall back to the footprints
                continue
            mesh.metadata["phirie_path"] = str(p)
            return mesh
    return None
