"""Object construction, end to end: ``run_objects(scene_dir, out_dir, config, strict)``.

Reads the observation stage's outputs in ``out_dir`` (``manifest.json`` ``instances`` and
``observe/instance_<id>.npz``) and, per instance:

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

Writes the manifest ``objects`` section (DESIGN.md "Contracts"), a ``construct`` record
(gravity frame, supports, config) and timings ``objects`` / ``objects.<step>``. A failure
of one object is recorded (status "failed" with the reason) and the rest go on.
"""

from __future__ import annotations

import dataclasses
import math
import time
import traceback
from collections.abc import Callable
from pathlib import Path

import numpy as np

from phirie_jax.construct.objects import assets
from phirie_jax.construct.objects.candidates import Candidate, candidate_pool
from phirie_jax.construct.objects.checks import candidate_checks, failed, first_by_priority, hull_volume, rank, rank_key
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
from phirie_jax.construct.objects.support import GravityFrame, Support, find_support, gravity_frame, refine_frame
from phirie_jax.errors import SceneInputError
from phirie_jax.io.scene import load_scene
from phirie_jax.manifest import Manifest, to_dict
from phirie_jax.types import GaussianSplatData, SceneInput


class _Clock:
    """Accumulated seconds per step."""

    def __init__(self):
        self.seconds: dict[str, float] = {}

    def add(self, step: str, since: float) -> None:
        self.seconds[step] = self.seconds.get(step, 0.0) + time.perf_counter() - since


def _up_guess(manifest: Manifest, scene: SceneInput) -> tuple[np.ndarray, str]:
    auto = (manifest.get("observe") or {}).get("auto") or {}
    if auto.get("up") is not None:
        return np.asarray(auto["up"], np.float64), "observe (automatic masks)"
    if scene.cameras:
        from phirie_jax.observe.auto import camera_up

        return camera_up(list(scene.cameras)), "cameras (mean image up)"
    return np.array([0.0, 0.0, 1.0]), "default +z"


def _raycaster(manifest: Manifest, scene: SceneInput, out_dir: Path):
    """The surface the observation stage lifted onto (scan mesh or its splat-derived one), or None."""
    import trimesh

    from phirie_jax.observe.raycast import Raycaster

    surface = (manifest.get("observe") or {}).get("surface") or {}
    path = surface.get("path")
    path = None if path is None else (Path(path) if Path(path).is_absolute() else out_dir / path)
    for p in (path, scene.surface_mesh):
        if p is not None and Path(p).is_file():
            try:
                mesh = trimesh.load(p, force="mesh", process=False)
                return Raycaster(mesh.vertices, mesh.faces), str(p)
            except (ValueError, OSError):
                continue
    return None, None


def _instance_input(record: dict, points: np.ndarray, data: dict, frame: GravityFrame, support: Support,
                    scene: SceneInput, out_dir: Path) -> InstanceInput:
    cams, paths, labels = [], [], []
    for view, path, label in zip(data["views"], data["mask_paths"], data["labels"]):
        if not str(path) or not 0 <= int(view) < len(scene.cameras):
            continue
        p = Path(str(path))
        cams.append(scene.cameras[int(view)])
        paths.append(p if p.is_absolute() else out_dir / p)
        labels.append(int(label))
    return InstanceInput(int(record["id"]), frame.to_gravity(points), frame, support, tuple(cams), tuple(paths),
                         tuple(labels))


# --- one candidate -------------------------------------------------------------------------


def _entry(candidate: Candidate) -> dict:
    return {**candidate.record(), "status": "failed" if candidate.error else "ok", "reason": candidate.error}


def _with_checks(entry: dict, h: Hypothesis, volume: float, config: ObjectsConfig) -> dict:
    checks = candidate_checks(h.scores(), volume, config)
    return {**entry, "scores": h.scores(), "checks": checks, "gravity_matrix": h.matrix}


def register_candidate(candidate: Candidate, obs: Observation, config: ObjectsConfig, clock: _Clock) -> dict:
    """Registration, checks and the bounded retry of one candidate → its manifest record."""
    entry = _entry(candidate)
    if not candidate.ok:
        return entry
    rc = config.registration
    t0 = time.perf_counter()
    model = sample_model(candidate.vertices, candidate.faces, rc.points, rc.seed)
    volume = hull_volume(candidate.vertices)
    clock.add("objects.sample", t0)
    t0 = t_reg = time.perf_counter()
    calls = 0
    if candidate.placement is not None:
        hyps = [score_placement(model, obs, candidate.placement, rc)]
        calls += 1
    else:
        first_axes = ALL_AXES if (rc.batched_retry and config.retry) else OWN_AXIS
        hyps, _ = search(model, obs, rc, first_axes, snap=config.snap_to_support)
        calls += 1
    clock.add("objects.register", t0)
    hyps = [h for h in hyps if h.finite]
    if not hyps:
        return {**entry, "status": "failed", "reason": "registration gave no finite placement", "kernel_calls": calls}
    own = _with_checks(entry, hyps[0], volume, config)
    retry = {"used": False}
    chosen = own
    if candidate.placement is None and config.retry and failed(own["checks"]):
        if len(hyps) == 1:  # lazy retry: the other five axes in a second call
            t0 = time.perf_counter()
            more, _ = search(model, obs, rc, OTHER_AXES, snap=config.snap_to_support)
            clock.add("objects.register", t0)
            calls += 1
            hyps += [h for h in more if h.finite]
        options = [own] + [_with_checks(entry, h, volume, config) for h in hyps[1:]]
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
                  config: ObjectsConfig, out_dir: Path) -> dict:
    m = chosen["gravity_matrix"]
    placed = candidate.vertices @ m[:3, :3].T + m[:3, 3]
    frame = assets.asset_frame(placed, inst.frame.matrix(), m)
    canon = placed - frame.base
    folder = out_dir / "objects" / str(inst.id)
    assets.write_obj(folder / "mesh.obj", canon, candidate.faces)
    visual: dict = {}
    splats = None
    if candidate.gaussians is not None:
        try:
            splats = assets.candidate_gaussians(candidate.gaussians, frame.candidate_to_canonical)
            visual = {"source": "candidate", "path": str(candidate.gaussians), "gaussians": splats.num}
        except (SceneInputError, OSError, ValueError) as err:
            visual = {"candidate_gaussians_failed": str(err)}
    if splats is None and scene.gaussians is not None:
        g = scene.gaussians
        height = inst.frame.to_gravity(g.means.astype(np.float64))[:, 2] - inst.support.height
        surface = sample_model(canon, candidate.faces, config.registration.points, config.registration.seed)
        surface_world = surface.astype(np.float64) @ frame.pose[:3, :3].T + frame.pose[:3, 3]
        idx = assets.captured_gaussians(g, q_world, surface_world, height, config.gaussian_radius,
                                        config.base_clearance)
        kept = assets.transform_splats(g.subset(idx), np.linalg.inv(frame.pose))
        fill, fill_info = assets.fill_gaussians(canon, candidate.faces, kept, config.fill_spacing,
                                                config.fill_min_distance, config.colour_neighbours, inst.id)
        splats = GaussianSplatData.join([kept, fill]) if kept.num else fill
        visual.update(source="captured", captured=int(kept.num), filled=int(fill.num), fill=fill_info)
    if splats is not None:
        assets.write_visual(folder / "visual.ply", splats)
    return {"pose": frame.pose, "source_pose": inst.frame.matrix() @ m,
            "candidate_to_canonical": frame.candidate_to_canonical,
            "mesh": f"objects/{inst.id}/mesh.obj",
            "visual": f"objects/{inst.id}/visual.ply" if splats is not None else None,
            "visual_info": visual}


def _entry_for(instance_id: int, reason: str | None = None) -> dict:
    """An ``objects`` entry with every contract field (DESIGN.md), failed until filled in.
    ``collision``, ``mass``, ``friction`` and ``drop_test`` are the physics stage's."""
    return {"id": int(instance_id), "status": "failed", "reason": reason, "candidate": None, "pose": None,
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


def construct_object(record: dict, q_world: np.ndarray, inst: InstanceInput, scene: SceneInput,
                     config: ObjectsConfig, out_dir: Path, clock: _Clock,
                     settle: Callable | None = None) -> dict:
    """The manifest ``objects`` entry of one instance (writes its asset files when accepted).
    With ``settle``, every candidate is drop-tested before ranking (settling check)."""
    out = {**_entry_for(inst.id), "support": {"height": inst.support.height, "source": inst.support.source}}
    if len(q_world) < config.min_points:
        return {**out, "reason": f"too few observed points ({len(q_world)} < min_points {config.min_points})"}
    t0 = time.perf_counter()
    pool = candidate_pool(inst, scene.candidates.get(inst.id, ()), config)
    clock.add("objects.candidates", t0)
    obs = prepare_observation(inst.points, inst.support.height, inst.support.source == "surface",
                              config.registration)
    entries = [register_candidate(c, obs, config, clock) for c in pool]
    for e in entries:
        e["pose"] = None if "gravity_matrix" not in e else inst.frame.matrix() @ e["gravity_matrix"]
    if settle is not None:
        t0 = time.perf_counter()
        settle_candidates(entries, pool, inst.frame.up, record.get("category"), settle)
        clock.add("objects.settle", t0)
    chosen = _select(entries, config)
    for position, e in enumerate(rank(entries)):
        e["rank"] = position
    out["candidates"] = [{k: v for k, v in e.items() if k != "gravity_matrix"} for e in entries]
    if chosen is None:
        reasons = "; ".join(f"{e['name']}: {e['reason']}" for e in entries) or "the candidate pool is empty"
        return {**out, "reason": f"no candidate could be registered ({reasons})"}
    bad = failed(chosen["checks"])
    out.update(candidate=chosen["name"], checks=chosen["checks"], unresolved_checks=bad)
    if config.strict and bad:
        return {**out, "status": "rejected", "reason": f"strict: failed checks {bad} on the best candidate"}
    t0 = time.perf_counter()
    candidate = next(c for c in pool if c.name == chosen["name"])
    files = _write_assets(chosen, candidate, inst, q_world, scene, config, out_dir)
    clock.add("objects.assets", t0)
    out.update({k: v for k, v in files.items()}, status="accepted",
               reason=None if not bad else f"kept with failed checks {bad} (use --strict to reject)")
    return out


def run_objects(scene_dir: str | Path, out_dir: str | Path, config: ObjectsConfig | None = None,
                strict: bool = False, scene: SceneInput | None = None,
                settle: Callable | None = None) -> dict:
    """Construct every observed instance's object (see the module docstring). Returns the manifest.

    ``settle``: the candidates' settling check (``construct.physics.settling.candidate_settler``,
    which the pipeline passes); None leaves that check "not run".
    """
    out_dir = Path(out_dir)
    config = config or ObjectsConfig()
    if strict and not config.strict:
        config = dataclasses.replace(config, strict=True)
    manifest = Manifest.load_or_create(out_dir)
    instances = manifest.require("instances", "the observation stage")
    start = time.perf_counter()
    clock = _Clock()
    scene = scene or load_scene(scene_dir, check_images=False)
    up, up_source = _up_guess(manifest, scene)
    frame = gravity_frame(up, up_source)
    raycaster, surface_path = _raycaster(manifest, scene, out_dir)
    loaded, objects = [], []
    for record in instances:
        try:
            data = dict(np.load(out_dir / record["points"]))
            loaded.append((record, data["points"].astype(np.float64), data))
        except (OSError, KeyError, ValueError) as err:
            objects.append(_entry_for(record["id"], f"observed points unreadable: {err}"))
    t0 = time.perf_counter()
    supports = [find_support(frame.to_gravity(q), frame, raycaster) for _, q, _ in loaded]
    frame = refine_frame(frame, supports)
    supports = [find_support(frame.to_gravity(q), frame, raycaster) for _, q, _ in loaded]
    clock.add("objects.frame", t0)
    for (record, q, data), support in zip(loaded, supports):
        t_obj = time.perf_counter()
        try:
            inst = _instance_input(record, q, data, frame, support, scene, out_dir)
            entry = construct_object(record, q, inst, scene, config, out_dir, clock, settle)
        except Exception as err:  # noqa: BLE001 — one object's failure is recorded, the scene goes on
            entry = {**_entry_for(record["id"], f"{type(err).__name__}: {err}"),
                     "traceback": traceback.format_exc(limit=4)}
        entry["time_s"] = time.perf_counter() - t_obj
        objects.append(entry)
    objects.sort(key=lambda o: o["id"])
    stale = assets.remove_stale_object_folders(out_dir, {o["id"] for o in objects if o.get("mesh")})
    manifest.set("objects", objects)
    manifest.set("construct", {
        "gravity": {"up": frame.up, "source": frame.source}, "surface": surface_path,
        "supports": [{"id": r["id"], "height": s.height, "source": s.source, "hits": s.hits}
                     for (r, _, _), s in zip(loaded, supports)],
        "strict": config.strict, "config": to_dict(config), "stale_object_folders": stale})
    for step, seconds in clock.seconds.items():
        manifest.record_timing(step, seconds)
    manifest.record_timing("objects", time.perf_counter() - start)
    manifest.write()
    return manifest.data


def summary(manifest: dict) -> dict:
    """Counts by status, for the CLI's one-line report."""
    objects = manifest.get("objects", [])
    counts = {s: sum(o["status"] == s for o in objects) for s in ("accepted", "rejected", "failed")}
    return {**counts, "seconds": manifest.get("timings", {}).get("objects", math.nan)}
