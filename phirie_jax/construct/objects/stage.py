"""Object construction, end to end: ``construct_objects(instances, up, scene, out_dir, config, settle)``
(``run_objects(scene_dir, out_dir, ...)`` on an output folder alone).

Takes the observation stage's records (``records.InstanceRecord``) and their files in ``out_dir``
(``observe/instance_<id>.npz``) and, per instance:

1. candidates: external files from ``candidates/<id>/`` and the built-in generators, in the
   configured pool order (``construct.candidates``);
2. registration: external candidates are searched over 6 signed up axes × 36 yaws × scales
   in one batched kernel call, then refined (``construct.register``); built-ins are scored
   where they were built;
3. checks per candidate (``construct.checks``); the candidate's own up (+z) is used unless
   its checks fail, when the bounded retry takes the best of the 5 other axes by the
   ranking key;
4. selection: lexicographic ranking on the checks ("evidence") or the fixed-priority
   baseline; ``strict`` rejects an object whose chosen candidate fails a check;
5. assets: ``objects/<id>/mesh.obj`` (canonical) and ``objects/<id>/visual.ply``
   (``construct.assets``).

Folders ``objects/<id>/`` that a previous run into the same ``out_dir`` wrote for objects
this run has no assets for are removed (only when they hold nothing but the stages' files).

Works in the scene's frame (``phirie_jax.frame``: metres, up as the frame records it, +z for
every scene converted with one). Returns an ``ObjectRecord`` per instance (the manifest's
``objects``, docs/architecture.md "Contracts") and the ``construct`` detail (supports, config);
timings ``objects`` / ``objects.<step>``. A failure of one object is recorded (status "failed"
with the reason) and the rest go on.
"""

from __future__ import annotations

import dataclasses
import time
import traceback
from collections.abc import Callable
from pathlib import Path

import numpy as np

from phirie_jax import layout
from phirie_jax.construct.objects import assets
from phirie_jax.construct.objects.candidates import Candidate, candidate_pool
from phirie_jax.construct.objects.checks import (
    candidate_checks,
    discovered_rejection,
    failed,
    first_by_priority,
    hull_volume,
    kept_reason,
    mount_check,
    mount_of,
    rank,
    rank_key,
    settling_welded,
)
from phirie_jax.construct.objects.config import ObjectsConfig
from phirie_jax.construct.objects.generators import InstanceInput
from phirie_jax.construct.objects.register import (
    ALL_AXES,
    OTHER_AXES,
    OWN_AXIS,
    Hypothesis,
    Observation,
    prepare_observation,
    sample_model,
    score_placement,
    search,
)
from phirie_jax.errors import SceneInputError
from phirie_jax.frame.gravity import GravityFrame, gravity_frame
from phirie_jax.frame.resolve import scene_in_world
from phirie_jax.io.mesh import read_mesh
from phirie_jax.io.scene import load_scene
from phirie_jax.manifest import ACCEPTED, FAILED_OBJECT, REJECTED, UNVERIFIED, Manifest, Timings, to_dict
from phirie_jax.observe.support import Support, Wall, find_support
from phirie_jax.records import InstanceRecord, ObjectRecord, plain
from phirie_jax.threads import map_on_cores
from phirie_jax.types import GaussianSplatData, SceneInput


def _raycaster(observed_surface: Path | None, scene: SceneInput):
    """The surface the observation stage lifted onto (``observed_surface``, or the scan mesh) as
    a raycaster, and its path; (None, None) without one."""
    from phirie_jax.observe.raycast import Raycaster

    for path in (observed_surface, scene.surface_mesh):
        if path is not None and Path(path).is_file():
            try:
                vertices, faces = read_mesh(path)
                return Raycaster(vertices, faces), str(path)
            except SceneInputError:
                continue
    return None, None


def _instance_input(record: InstanceRecord, points: np.ndarray, data: dict, frame: GravityFrame, support: Support,
                    scene: SceneInput, out_dir: Path, surface=None) -> InstanceInput:
    cams, paths, labels = [], [], []
    for view, path, label in zip(data["views"], data["mask_paths"], data["labels"]):
        if not str(path) or not 0 <= int(view) < len(scene.cameras):
            continue
        p = Path(str(path))
        cams.append(scene.cameras[int(view)])
        paths.append(p if p.is_absolute() else out_dir / p)
        labels.append(int(label))
    return InstanceInput(int(record.id), frame.to_gravity(points), frame, support, tuple(cams), tuple(paths),
                         tuple(labels), surface)


# --- one candidate -------------------------------------------------------------------------


def _entry(candidate: Candidate) -> dict:
    return {**candidate.record(), "status": "failed" if candidate.error else "ok", "reason": candidate.error}


def _with_checks(entry: dict, h: Hypothesis, volume: float, config: ObjectsConfig, size: float) -> dict:
    checks = candidate_checks(h.scores(), volume, config, size)
    return {**entry, "scores": h.scores(), "checks": checks, "gravity_matrix": h.matrix}


def register_candidate(candidate: Candidate, obs: Observation, config: ObjectsConfig,
                       timings: Timings | None = None, size_bound: bool = True) -> dict:
    """Registration, checks and the bounded retry of one candidate → its record (``candidates[]``);
    ``timings``: where ``objects.sample`` and ``objects.register`` add up (None: not kept);
    ``size_bound``: the registration bound may grow with the object's size (``checks.residual_threshold``;
    False: ``max_residual`` alone, for what automatic discovery found: no user says it is an object,
    and a duvet's fold fits a heightfield within a few per cent of its size too)."""
    timings = timings if timings is not None else Timings()
    entry = _entry(candidate)
    if not candidate.ok:
        return entry
    rc = config.registration
    with timings.timed("objects.sample"):
        model = sample_model(candidate.vertices, candidate.faces, rc.points, rc.seed)
        volume = hull_volume(candidate.vertices)
    t_reg = time.perf_counter()
    with timings.timed("objects.register"):
        if candidate.placement is not None:
            hyps = [score_placement(model, obs, candidate.placement, rc)]
        else:
            first_axes = ALL_AXES if (rc.batched_retry and config.retry) else OWN_AXIS
            hyps, _ = search(model, obs, rc, first_axes, snap=config.snap_to_support)
    calls = 1
    hyps = [h for h in hyps if h.finite]
    if not hyps:
        return {**entry, "status": "failed", "reason": "registration gave no finite placement", "kernel_calls": calls}
    size = obs.size if size_bound else 0.0
    own = _with_checks(entry, hyps[0], volume, config, size)
    retry = {"used": False}
    chosen = own
    if candidate.placement is None and config.retry and failed(own["checks"]):
        if len(hyps) == 1:  # lazy retry: the other five axes in a second call
            with timings.timed("objects.register"):
                more, _ = search(model, obs, rc, OTHER_AXES, snap=config.snap_to_support)
            calls += 1
            hyps += [h for h in more if h.finite]
        options = [own] + [_with_checks(entry, h, volume, config, size) for h in hyps[1:]]
        chosen = min(options, key=rank_key)
        retry = {"used": True, "own_up_failed": failed(own["checks"]), "chosen_axis": chosen["scores"]["axis"],
                 "axes": [{"axis": o["scores"]["axis"], "energy": o["scores"]["energy"],
                           "failed_checks": failed(o["checks"])} for o in options]}
    return {**chosen, "retry": retry, "kernel_calls": calls, "register_s": time.perf_counter() - t_reg}


# --- one object --------------------------------------------------------------------------


def _select(entries: list[dict], config: ObjectsConfig) -> dict | None:
    if config.selection == "priority":
        return first_by_priority(entries)
    ranked = rank(entries)
    return ranked[0] if ranked else None


def _write_assets(chosen: dict, candidate: Candidate, inst: InstanceInput, q_world: np.ndarray, scene: SceneInput,
                  config: ObjectsConfig, out_dir: Path, surface=None) -> dict:
    """``objects/<id>/mesh.obj`` (canonical) and ``visual.ply`` of the chosen candidate → the entry's
    asset fields."""
    m = chosen["gravity_matrix"]
    placed = candidate.vertices @ m[:3, :3].T + m[:3, 3]
    frame = assets.asset_frame(placed, inst.frame.matrix(), m)
    canon = placed - frame.base
    assets.write_obj(out_dir / layout.object_file(inst.id, layout.OBJECT_MESH), canon, candidate.faces)
    splats, visual = _visual_gaussians(candidate, canon, frame, inst, q_world, scene, config, surface)
    if splats is not None:
        assets.write_visual(out_dir / layout.object_file(inst.id, layout.OBJECT_VISUAL), splats)
    return {"pose": frame.pose, "source_pose": inst.frame.matrix() @ m,
            "candidate_to_canonical": frame.candidate_to_canonical,
            "mesh": layout.object_file(inst.id, layout.OBJECT_MESH),
            "visual": layout.object_file(inst.id, layout.OBJECT_VISUAL) if splats is not None else None,
            "visual_info": visual}


def _visual_gaussians(candidate: Candidate, canon: np.ndarray, frame: assets.AssetFrame, inst: InstanceInput,
                      q_world: np.ndarray, scene: SceneInput, config: ObjectsConfig, surface=None
                      ) -> tuple[GaussianSplatData | None, dict]:
    """The object's own Gaussians in its canonical frame: the candidate's when it brought some,
    else the capture's around the placed surface plus fill disks where none were captured and no
    camera saw that part of the object or (with the scene ``surface``, a ``Raycaster``) through it:
    what a camera saw of the object is the captured Gaussians' to show, even where the completed
    shape is off (a disk there would show through their gaps or stand in front of them)."""
    from phirie_jax.observe.raycast import Raycaster

    visual: dict = {}
    if candidate.gaussians is not None:
        try:
            splats = assets.candidate_gaussians(candidate.gaussians, frame.candidate_to_canonical)
            return splats, {"source": "candidate", "path": str(candidate.gaussians), "gaussians": splats.num}
        except (SceneInputError, OSError, ValueError) as err:
            visual = {"candidate_gaussians_failed": str(err)}
    if scene.gaussians is None:
        return None, visual
    g = scene.gaussians
    height = inst.frame.to_gravity(g.means.astype(np.float64))[:, 2] - inst.support.height
    placed = Raycaster(canon @ frame.pose[:3, :3].T + frame.pose[:3, 3], candidate.faces)
    idx = assets.captured_gaussians(g, q_world, placed, height, config.gaussian_radius, config.base_clearance,
                                    config.gaussian_mesh_radius)
    kept = assets.transform_splats(g.subset(idx), np.linalg.inv(frame.pose))
    seen = _seen(inst, placed, surface, frame.pose, config.fill_min_distance)
    fill, fill_info = assets.fill_gaussians(canon, candidate.faces, kept, config.fill_spacing,
                                            config.fill_min_distance, config.colour_neighbours, inst.id, seen)
    visual.update(source="captured", captured=int(kept.num), filled=int(fill.num), fill=fill_info)
    return (GaussianSplatData.join([kept, fill]) if kept.num else fill), visual


def _seen(inst: InstanceInput, placed, surface, pose: np.ndarray, tolerance: float):
    """(P, 3) canonical points → (P,) bool: some view of the instance has the point inside the
    instance's mask on the side of the placed mesh that view sees (``placed``, a ``Raycaster`` of it
    in the scene: the captured Gaussians are that side's appearance), or, with the scene
    ``surface``, has it in the image with the surface more than ``tolerance`` beyond it (the camera
    saw through it: free space, whatever the mask says there)."""
    from phirie_jax.observe.masks import read_label_png

    def seen(points: np.ndarray) -> np.ndarray:
        world = points @ pose[:3, :3].T + pose[:3, 3]
        out = np.zeros(len(points), bool)
        for camera, path, label in zip(inst.cameras, inst.mask_paths, inst.labels):
            try:
                mask = read_label_png(path, camera) == label
            except (SceneInputError, OSError, ValueError):
                continue
            uv, depth = camera.project(world)
            col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
            ok = (depth > 0) & (col >= 0) & (row >= 0) & (col < mask.shape[1]) & (row < mask.shape[0]) & ~out
            if surface is not None and ok.any():
                # anywhere in the image: a camera that saw the surface beyond a point saw free space
                out[np.flatnonzero(ok)] |= surface.seen_through(world[ok], camera, tolerance)
                ok &= ~out
            ok[ok] &= mask[row[ok], col[ok]]
            if ok.any():
                out[np.flatnonzero(ok)] |= placed.faces_camera(world[ok], camera, tolerance)
        return out

    return seen


def _entry_for(instance_id: int, reason: str | None = None) -> dict:
    """An ``objects`` entry with every contract field (docs/architecture.md "Contracts"), failed until filled in.
    ``collision``, ``mass``, ``friction`` and ``drop_test`` are the physics stage's."""
    return {"id": int(instance_id), "status": FAILED_OBJECT, "reason": reason, "candidate": None, "pose": None,
            "mesh": None, "visual": None, "collision": [], "mass": None, "friction": None, "checks": {},
            "candidates": [], "drop_test": None}


def settle_candidates(entries: list[dict], pool: list[Candidate], up: np.ndarray, category: str | None,
                      settle: Callable) -> None:
    """Drop-test every registered candidate at its placement (``settle``: physics's
    ``CandidateSettler``) and fill in its settling check, so ranking sees it."""
    by_name = {c.name: c for c in pool}
    placed = [e for e in entries if e.get("pose") is not None and e["name"] in by_name]
    if not placed:
        return
    meshes = [(by_name[e["name"]].vertices, by_name[e["name"]].faces) for e in placed]
    for e, row in zip(placed, settle(meshes, [e["pose"] for e in placed], up, category)):
        e["checks"] = {**e["checks"], "settling": row}


def mount_candidates(entries: list[dict], pool: list[Candidate], wall: Wall, config: ObjectsConfig) -> None:
    """The check tables of a mounted object's registered candidates: its mount check, and its
    settling left to the physics stage's hold test (a free drop test would show only the fall)."""
    by_name = {c.name: c for c in pool}
    for e in entries:
        if e.get("pose") is None or e["name"] not in by_name or not e.get("checks"):
            continue
        pose = np.asarray(e["pose"], np.float64)
        placed = by_name[e["name"]].vertices @ pose[:3, :3].T + pose[:3, 3]
        e["checks"] = {**e["checks"], "settling": settling_welded(config), "mount": mount_check(placed, wall, config)}


def construct_object(record: InstanceRecord, q_world: np.ndarray, inst: InstanceInput, scene: SceneInput,
                     config: ObjectsConfig, out_dir: Path, timings: Timings,
                     settle: Callable | None = None, surface=None) -> dict:
    """The manifest ``objects`` entry of one instance (writes its asset files when accepted).
    With ``settle``, every candidate is drop-tested before ranking (settling check); with the
    scene ``surface`` (a ``Raycaster``), no fill disk goes where a camera saw through."""
    gap = base_gap(inst)
    mount = mount_of(Wall.from_record(record.extra.get("wall")), gap, config)
    out = {**_entry_for(inst.id), "support": {"height": inst.support.height, "source": inst.support.source,
                                              "gap_m": round(gap, 4)},
           **({"mount": mount.as_record()} if mount is not None else {})}
    if len(q_world) < config.min_points:
        return {**out, "reason": f"too few observed points ({len(q_world)} < min_points {config.min_points})"}
    with timings.timed("objects.candidates"):
        pool = candidate_pool(inst, scene.candidates.get(inst.id, ()), config)
    entries = _registered(pool, inst, config, timings, size_bound=record.source != "auto")
    if mount is not None:
        mount_candidates(entries, pool, mount, config)
    elif settle is not None:
        with timings.timed("objects.settle"):
            settle_candidates(entries, pool, inst.frame.up, record.category, settle)
    chosen = _select(entries, config)
    for position, e in enumerate(rank(entries)):
        e["rank"] = position
    out["candidates"] = [{k: v for k, v in e.items() if k != "gravity_matrix"} for e in entries]
    if chosen is None:
        reasons = "; ".join(f"{e['name']}: {e['reason']}" for e in entries) or "the candidate pool is empty"
        return {**out, "reason": f"no candidate could be registered ({reasons})"}
    bad = failed(chosen["checks"])
    out.update(candidate=chosen["name"], checks=chosen["checks"], unresolved_checks=bad)
    discovered = discovered_rejection(record.source, bad, gap, config.settle_threshold)
    if discovered:
        return {**out, "status": REJECTED, "reason": discovered}
    if config.strict and bad:
        return {**out, "status": REJECTED, "reason": f"strict: failed checks {bad} on the best candidate"}
    candidate = next(c for c in pool if c.name == chosen["name"])
    with timings.timed("objects.assets"):
        files = _write_assets(chosen, candidate, inst, q_world, scene, config, out_dir, surface)
    return {**out, **files, "status": UNVERIFIED if bad else ACCEPTED,
            "reason": kept_reason(bad, gap, config.settle_threshold, mount is not None)}


def base_gap(inst: InstanceInput) -> float:
    """How far the instance's lowest observed points (1st percentile along up) are above its support."""
    return float(np.percentile(inst.points[:, 2], 1)) - inst.support.height if len(inst.points) else 0.0


def _registered(pool: list[Candidate], inst: InstanceInput, config: ObjectsConfig, timings: Timings,
                size_bound: bool = True) -> list[dict]:
    """Every candidate of the pool registered and checked (``register_candidate``), its placement as
    a world pose."""
    obs = prepare_observation(inst.points, inst.support.height, inst.support.source in ("surface", "prompt"),
                              config.registration, cut=inst.support.clearance)
    entries = [register_candidate(c, obs, config, timings, size_bound) for c in pool]
    for e in entries:
        e["pose"] = None if "gravity_matrix" not in e else inst.frame.matrix() @ e["gravity_matrix"]
    return entries


# --- the stage ---------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _Observed:
    record: InstanceRecord
    points: np.ndarray  # (N, 3) world Q_i
    data: dict          # its ``observe/instance_<id>.npz`` arrays


def _load_instances(instances: tuple[InstanceRecord, ...], out_dir: Path) -> tuple[list[_Observed], list[dict]]:
    """Each instance's observed points; an unreadable file makes that object failed."""
    loaded, failures = [], []
    for record in instances:
        try:
            data = dict(np.load(out_dir / record.points))
            loaded.append(_Observed(record, data["points"].astype(np.float64), data))
        except (OSError, KeyError, ValueError) as err:
            failures.append(_entry_for(record.id, f"observed points unreadable: {err}"))
    return loaded, failures


def _frame_and_supports(up: np.ndarray, loaded: list[_Observed], raycaster) -> tuple[GravityFrame, list[Support]]:
    """The scene's gravity frame (up as decided once, ``phirie_jax.frame``) and each instance's
    support under it (as observation found it; found here for an observation that did not record it)."""
    frame = gravity_frame(up, "scene frame")
    return frame, [Support.from_record(o.record.support) if o.record.support
                   else find_support(frame.to_gravity(o.points), frame, raycaster) for o in loaded]


def _construct_each(loaded: list[_Observed], frame: GravityFrame, supports: list[Support], scene: SceneInput,
                    config: ObjectsConfig, out_dir: Path, timings: Timings, settle: Callable | None,
                    surface=None) -> list[dict]:
    """``construct_object`` of every instance, ``ObjectsConfig.workers`` at once (threads: the
    numerical work releases the interpreter, each object writes only its own folder, and the
    entries come back in instance order); one object's failure is recorded, the rest go on. The
    ``objects.<step>`` timings then sum the threads' time."""
    def one(pair: tuple[_Observed, Support]) -> dict:
        o, support = pair
        start = time.perf_counter()
        try:
            inst = _instance_input(o.record, o.points, o.data, frame, support, scene, out_dir, surface)
            entry = construct_object(o.record, o.points, inst, scene, config, out_dir, timings, settle, surface)
        except Exception as err:  # noqa: BLE001 — one object's failure is recorded, the scene goes on
            entry = {**_entry_for(o.record.id, f"{type(err).__name__}: {err}"),
                     "traceback": traceback.format_exc(limit=4)}
        entry["time_s"] = time.perf_counter() - start
        return entry

    return map_on_cores(one, zip(loaded, supports), "objects", config.workers)


def _construct_record(surface_path: str | None, loaded: list[_Observed], supports: list[Support],
                      config: ObjectsConfig, stale: list) -> dict:
    """The object stage's own record (``construct``): the surface, the supports, the config."""
    return plain({"surface": surface_path,
                  "supports": [{"id": o.record.id, "height": s.height, "source": s.source, "hits": s.hits}
                               for o, s in zip(loaded, supports)],
                  "strict": config.strict, "config": to_dict(config), "stale_object_folders": stale})


def construct_objects(instances: tuple[InstanceRecord, ...], up: np.ndarray, scene: SceneInput,
                      out_dir: str | Path, config: ObjectsConfig | None = None, settle: Callable | None = None,
                      observed_surface: Path | None = None, timings: Timings | None = None
                      ) -> tuple[tuple[ObjectRecord, ...], dict]:
    """Construct every observed instance's object (see the module docstring) in the world of
    ``scene`` (up: (3,) its up, as the frame records it); writes the assets in ``out_dir`` and
    returns (the objects by id, the ``construct`` record).

    ``settle``: the candidates' settling check (``construct.physics.settling.candidate_settler``,
    which the pipeline passes); None leaves that check "not run". ``observed_surface``: the
    surface observation lifted onto. ``timings``: ``objects`` and ``objects.<step>``.
    """
    out_dir = Path(out_dir)
    config = config or ObjectsConfig()
    timings = timings if timings is not None else Timings()
    with timings.timed("objects"):
        raycaster, surface_path = _raycaster(observed_surface, scene)
        loaded, failures = _load_instances(instances, out_dir)
        with timings.timed("objects.supports"):
            frame, supports = _frame_and_supports(up, loaded, raycaster)
        objects = failures + _construct_each(loaded, frame, supports, scene, config, out_dir, timings, settle,
                                             raycaster)
        objects.sort(key=lambda o: o["id"])
        stale = assets.remove_stale_object_folders(out_dir, {o["id"] for o in objects if o.get("mesh")})
        record = _construct_record(surface_path, loaded, supports, config, stale)
    return tuple(ObjectRecord.from_json(plain(o)) for o in objects), record


def run_objects(scene_dir: str | Path, out_dir: str | Path, config: ObjectsConfig | None = None,
                scene: SceneInput | None = None, settle: Callable | None = None) -> dict:
    """The object stage on an output folder alone (``construct_objects``; the folder's manifest
    read and written, the scene loaded from ``scene_dir`` unless given). Returns the manifest."""
    manifest = Manifest.load_or_create(out_dir)
    instances = manifest.instances()  # the observation stage ran
    scene = scene or scene_in_world(load_scene(scene_dir, check_images=False), manifest.capture_to_world())
    objects, record = construct_objects(instances, manifest.up(), scene, out_dir, config, settle,
                                        manifest.observed_surface(), manifest.timings)
    manifest.set("objects", objects)
    manifest.set("construct", record)
    manifest.write()
    return manifest.data
