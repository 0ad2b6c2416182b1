"""The background branch, end to end: ``construct_background(objects, instances, up, supports, ...)``
(``run_background(scene_dir, out_dir, config)`` on an output folder alone).

Takes the capture G0, the earlier stages' records (``records.ObjectRecord``,
``records.InstanceRecord``) and their files in ``out_dir`` (``observe/instance_<id>.npz``, the
assets' ``objects/<id>/mesh.obj``), and for the objects being made movable:

1. removal, coupled to the object identity: R_i = R_obs ∪ R_asset ∪ R_mask (``removal``);
2. per object a robust support plane and the exposed cells of it (``plane``); where the kept
   Gaussians around the object give none, the level plane of the support the object stage found
   under it on the scene surface (``plane_source``) — no plane is an *unsupported region*,
   recorded, and that object's hole stays; cells that two views saw surface behind (past a
   draped support's edge) are not laid (``seethrough``);
3. inpainting targets: one primary view per object, all edits of a frame in one target
   (``targets``; exemplar patches by default, OpenCV Telea or Navier–Stokes, or an external editor's folder);
4. new disks on a ``grid`` lattice over the exposed cells plus a margin, coloured from the targets
   where a target sees them and from the neighbouring kept surface elsewhere, then refined — only
   they, the kept Gaussians fixed — against the targets (``refine``, ``kernels.fill``).

Writes ``background.ply`` (INRIA format) = (G0 \\ ∪R_i) ∪ G_fill, ``background/targets/`` (the
targets, editor format), and the manifest ``background`` section: ``path``, ``removed``,
``filled`` (docs/architecture.md "Contracts") and per object the counts of R_obs, R_asset, R_mask and their
union, the plane, the fill, the primary view and a status ("filled", "untargeted" — disks
coloured from neighbours only, no view sees them —, "nothing_exposed", "unsupported", "failed",
"skipped"), plus ``unsupported_regions``, ``failed_completions``, the frames, the refinement
record, the crop renders and the launches that rendered them, the XLA programs compiled
(``compiles``: count and seconds; it must not grow with the objects) and the config; timings
``background`` and ``background.<step>``. A failure of one object is recorded and the rest go on.
"""

from __future__ import annotations

import dataclasses
import traceback
from pathlib import Path

import numpy as np

from kernels.sh import SH_C0, rgb_to_sh_dc
from phirie_jax import layout
from phirie_jax.compile_count import CompileCount
from phirie_jax.construct.background import plane as fill_mod
from phirie_jax.construct.background import targets
from phirie_jax.construct.background.config import BackgroundConfig
from phirie_jax.construct.background.refine import DiskSet, refine
from phirie_jax.construct.background.removal import ObjectInput, load_object, removal_sets
from phirie_jax.construct.background.seethrough import see_through_votes
from phirie_jax.construct.background.views import CropRenderer, make_crop
from phirie_jax.construct.background.views import Footprints as CropFootprints
from phirie_jax.geometry import sigmoid
from phirie_jax.io.ply import write_gaussian_ply
from phirie_jax.io.scene import load_scene
from phirie_jax.manifest import Manifest, Timings, to_dict
from phirie_jax.observe.support import Support
from phirie_jax.records import BackgroundRecord, InstanceRecord, ObjectRecord, plain
from phirie_jax.types import Camera, GaussianSplatData, SceneInput

VISIBLE_TRANS = 0.5  # a target sees a disk where the front layer lets this much through
BASE_PERCENTILE = 2  # without a recorded support, an object's base is this percentile of Q_i's height


# --- the run's state --------------------------------------------------------------------------

@dataclasses.dataclass
class _Run:
    """What every step reads, and the records the steps add to (mutable on purpose: each step
    fills in its objects' records and appends to ``unsupported`` and ``failed``)."""

    out_dir: Path
    data: GaussianSplatData          # (N,) the capture G0
    cameras: tuple[Camera, ...]
    up: np.ndarray                   # (3,) unit
    crops: CropRenderer
    inputs: list[ObjectInput]        # the objects being removed
    records: dict[int, dict]         # per object id: the manifest record
    unsupported: list[dict] = dataclasses.field(default_factory=list)
    failed: list[dict] = dataclasses.field(default_factory=list)


@dataclasses.dataclass(frozen=True)
class _Kept:
    """The Gaussians that stay (G0 \\ ∪R_i) as the plane and fill steps read them."""

    means: np.ndarray    # (K, 3) float64
    opacity: np.ndarray  # (K,)
    rgb: np.ndarray      # (K, 3) SH DC colour in [0, 1]

    @classmethod
    def of(cls, data: GaussianSplatData) -> _Kept:
        return cls(data.means.astype(np.float64), sigmoid(data.opacity_logits),
                   np.clip(data.sh[:, 0].astype(np.float64) * SH_C0 + 0.5, 0, 1))


@dataclasses.dataclass(frozen=True)
class _Footing:
    """Where one object stands: its support's height along up and its points (Q_i and, registered,
    its asset's surface: its shadow on the support). What is evidence of where it meets the support
    is Q_i alone (the removal's sparing, the fill region): the asset's base is a completion nobody
    saw, verified or not: an extrusion down past a draped support's edge, a visual hull's cut
    through a duvet the plush sinks into (on snowmiku its base laid fill the held-out views saw
    around the plush: −0.53 dB against −0.23 dB with Q_i alone, at 500 px)."""

    base: float
    points: np.ndarray   # (P, 3)


@dataclasses.dataclass(frozen=True)
class _ObjectFill:
    """One object's fill region and its initial disks."""

    id: int
    region: fill_mod.FillRegion
    disks: GaussianSplatData  # (K,) SH DC only


def _fail(record: dict, status: str, reason: str, err: BaseException | None = None) -> None:
    record.update(status=status, reason=reason)
    if err is not None:
        record["traceback"] = traceback.format_exc(limit=4)


# --- the stage ----------------------------------------------------------------------------------

def run_background(scene_dir: str | Path, out_dir: str | Path, config: BackgroundConfig | None = None,
                   scene: SceneInput | None = None) -> dict:
    """The background stage on an output folder alone (``construct_background``; the folder's
    manifest read and written). Returns the manifest as a dict."""
    manifest = Manifest.load_or_create(out_dir)
    objects = manifest.require("objects", "the object-construction stage")
    manifest.set("background", construct_background(
        objects, manifest.get("instances", ()), manifest.up(), manifest.support_records(), scene_dir, out_dir, config,
        scene, manifest.timings))
    manifest.write()
    return manifest.data


def construct_background(objects: tuple[ObjectRecord, ...], instances: tuple[InstanceRecord, ...], up: np.ndarray,
                         supports: dict[int, dict], scene_dir: str | Path | None, out_dir: str | Path,
                         config: BackgroundConfig | None = None, scene: SceneInput | None = None,
                         timings: Timings | None = None) -> BackgroundRecord:
    """The background stage (module docstring) of ``objects`` observed as ``instances``, in the
    world of ``scene`` (else the folder ``scene_dir``; up: (3,) its up; supports: object id → the
    record of the support it stands on, ``Manifest.support_records``) → the ``background`` record."""
    out_dir = Path(out_dir)
    config = config or BackgroundConfig()
    timings = timings if timings is not None else Timings()
    with timings.timed("background"), CompileCount() as compiles:
        with timings.timed("background.load"):
            run = _load_inputs(scene_dir, out_dir, instances, up, objects, config, scene)
        support_of = {k: Support.from_record(r) for k, r in supports.items()}
        with timings.timed("background.removal"):
            footings = [_footing(run, o, support_of.get(o.id), config) for o in run.inputs]
            sets, removed = _removal(run, config, footings)
        with timings.timed("background.plane"):
            fills = _plane_fills(run, sets, removed, support_of, footings, config)
        if fills and config.fill.see_through_votes > 0:
            with timings.timed("background.see_through"):
                fills = _drop_seen_through(run, fills, config)
        fill_data, frames_record, refine_record = None, [], None
        if fills:
            with timings.timed("background.targets"):
                disk_set = _disk_set(fills)
                frames, frames_record = _frames(run, removed, disk_set, fills, config)
            if frames:
                with timings.timed("background.refine"):
                    disk_set = _colour_from_targets(run, disk_set, frames, fills)
                    if config.refine.iterations > 0:
                        fill_data, refine_record = refine(disk_set, frames, config, run.data.sh.shape[1])
            fill_data = disk_set.disks if fill_data is None else fill_data
            _mark_filled(run, fills)
        with timings.timed("background.write"):
            background, kept_num = _write(run, removed, fill_data)
        section = _section(run, config, removed, background, kept_num, frames_record, refine_record)
    return BackgroundRecord.from_json(plain({**section, "compiles": compiles.record()}))


def _load_inputs(scene_dir: str | Path | None, out_dir: Path, instance_records: tuple[InstanceRecord, ...],
                 up: np.ndarray, objects: tuple[ObjectRecord, ...], config: BackgroundConfig,
                 scene: SceneInput | None) -> _Run:
    """The capture, its cameras, up, and the inputs of the objects being removed (the others are
    recorded as skipped, those whose inputs cannot be read as failed)."""
    scene = scene or load_scene(scene_dir, check_images=False)
    data = scene.require_gaussians()
    cameras = scene.require_cameras()
    instances = {i.id: i for i in instance_records}
    records: dict[int, dict] = {}
    inputs: list[ObjectInput] = []
    for entry in objects:
        rec = records.setdefault(entry.id, {"id": entry.id, "status": None, "reason": None})
        if entry.status not in config.removal.statuses:
            _fail(rec, "skipped", f"object status {str(entry.status)!r}: its Gaussians stay in the background")
            continue
        try:
            if entry.id not in instances:
                raise KeyError(f"no instance {entry.id} in the manifest")
            inputs.append(load_object(entry, instances[entry.id], out_dir))
        except Exception as err:  # noqa: BLE001 — one object's failure is recorded, the scene goes on
            _fail(rec, "failed", f"inputs unreadable, not removed: {type(err).__name__}: {err}", err)
    return _Run(out_dir, data, cameras, up / np.linalg.norm(up), CropRenderer(), inputs, records)


def _removal(run: _Run, config: BackgroundConfig, footings: list[_Footing]) -> tuple[list[np.ndarray], np.ndarray]:
    """R_i of every object being removed (indices into G0) and (N,) bool: in any R_i."""
    contacts = [(f.base, o.q) for o, f in zip(run.inputs, footings)]
    sets, removal_records = (removal_sets(run.data, run.inputs, run.cameras, config, run.crops, run.up, contacts)
                             if run.inputs else ([], []))
    removed = np.zeros(run.data.num, bool)
    for o, r_i, rec in zip(run.inputs, sets, removal_records):
        removed[r_i] = True
        run.records[o.id]["removed"] = rec
    return sets, removed


def _plane_fills(run: _Run, sets: list[np.ndarray], removed: np.ndarray, supports: dict[int, Support],
                 footings: list[_Footing], config: BackgroundConfig) -> list[_ObjectFill]:
    """Per object its support plane, the exposed cells and their initial disks; an object without
    a plane, with nothing exposed or with too many disks is recorded and has no fill."""
    kept = _Kept.of(run.data.subset(~removed))
    index = fill_mod.BoxIndex(kept.means)  # each object's boxes read only their x-slab of the kept
    fills = []
    for o, r_i, footing in zip(run.inputs, sets, footings):
        rec = run.records[o.id]
        try:
            fill = _object_fill(run, o, r_i, kept, supports.get(o.id), footing, config, index)
        except Exception as err:  # noqa: BLE001
            reason = f"{type(err).__name__}: {err}"
            _fail(rec, "failed", reason, err)
            run.failed.append({"id": o.id, "reason": reason})
            continue
        if fill is not None:
            fills.append(fill)
    return fills


def _drop_seen_through(run: _Run, fills: list[_ObjectFill], config: BackgroundConfig) -> list[_ObjectFill]:
    """Each object's fill without the cells the cameras saw surface behind (``seethrough``);
    an object left with no cell is recorded and has no fill."""
    fill_config = config.fill
    votes = see_through_votes(run.data, run.cameras, [f.region.centres for f in fills], run.crops,
                              max_views=fill_config.see_through_views, crop_size=fill_config.see_through_crop,
                              depth_tolerance=fill_config.see_through_depth)
    out = []
    for f, v in zip(fills, votes):
        keep = v.through < fill_config.see_through_votes
        rec = run.records[f.id]
        rec["fill"]["see_through"] = v.record(int((~keep).sum()))
        rec["fill"]["disks"] = int(keep.sum())
        if not keep.any():
            _fail(rec, "nothing_exposed", "every fill cell was seen through to a surface behind it")
            continue
        out.append(_ObjectFill(f.id, f.region.subset(keep), f.disks.subset(np.flatnonzero(keep))))
    return out


def _footing(run: _Run, o: ObjectInput, support: Support | None, config: BackgroundConfig) -> _Footing:
    """``_Footing`` of one object; its base is the support recorded under it, else low in its Q_i."""
    base = support.height if support is not None else float(np.percentile(o.q @ run.up, BASE_PERCENTILE))
    points = fill_mod.object_points(o.q, o.mesh, config.fill.grid, config.seed)
    return _Footing(base, points)


def _object_fill(run: _Run, o: ObjectInput, r_i: np.ndarray, kept: _Kept, support: Support | None,
                 footing: _Footing, config: BackgroundConfig, index: fill_mod.BoxIndex | None = None
                 ) -> _ObjectFill | None:
    """One object's plane, fill region and disks (``plane``); None, recorded, when it has none.
    r_i: (R,) its removed Gaussians; support: what observation found it stands on, if recorded;
    index: ``plane.BoxIndex(kept.means)``."""
    rec = run.records[o.id]
    obj_pts, base = footing.points, footing.base
    ring = fill_mod.ring_points(kept.means, kept.opacity, obj_pts, run.up, base, config, index)
    centre = o.q.mean(0)
    anchor = centre + (base - centre @ run.up) * run.up
    plane, reason = fill_mod.fit_plane(kept.means[ring], run.up, config, anchor)
    if plane is None and support is not None and support.is_plane:
        # The kept Gaussians around it give no plane (optimizer-shaped Gaussians describe a tabletop
        # with few, large, semi-transparent ones; a neighbour's lower half fills the ring): the
        # support the object stage found under it on the scene surface, level.
        plane = fill_mod.Plane(anchor, np.asarray(run.up, np.float64), 0, len(ring), 0.0)
        rec["plane_source"] = f"observed support: {reason}"
    if plane is None:
        _fail(rec, "unsupported", reason)
        run.unsupported.append({"id": o.id, "reason": reason, "ring_points": len(ring), "removed": len(r_i)})
        return None
    rec.setdefault("plane_source", "ring")
    rec["plane"] = plane.as_dict()
    region = fill_mod.fill_region(plane, kept.means, kept.opacity, obj_pts,
                                  run.data.means[r_i].astype(np.float64), config, index, o.q)
    rec["fill"] = {"exposed_cells": region.exposed, "disks": region.num,
                   "kept_spacing_m": round(region.covered_spacing, 5)}
    if region.num == 0:
        _fail(rec, "nothing_exposed", "the kept surface covers the whole footprint")
        return None
    if region.num > config.fill.max_disks:
        reason = f"{region.num} disks exceed max_disks {config.fill.max_disks}"
        _fail(rec, "failed", reason)
        run.failed.append({"id": o.id, "reason": reason})
        return None
    on_plane = np.abs(plane.height(kept.means)) <= config.fill.slab
    colours = fill_mod.neighbour_colours(region.centres, kept.means[on_plane], kept.rgb[on_plane],
                                         config.fill.colour_neighbours)
    return _ObjectFill(o.id, region, fill_mod.disks(region, colours, config, 1))


def _disk_set(fills: list[_ObjectFill]) -> DiskSet:
    """Every object's disks in one set, with their in-plane axes and owners."""
    tangents = [np.broadcast_to(np.stack([f.region.u, f.region.v]), (f.region.num, 2, 3)) for f in fills]
    return DiskSet(GaussianSplatData.join([f.disks for f in fills], like=fills[0].disks),
                   np.concatenate(tangents).astype(np.float32),
                   np.concatenate([np.full(f.region.num, f.id) for f in fills]))


def _target_colours(disks: GaussianSplatData, owner: np.ndarray, frames: list[targets.Frame]) -> np.ndarray:
    """(N, 3) colour of each disk's pixel in the first frame that sees it (its own object's frames
    first), NaN where none does. owner: (N,) object id of each disk."""
    out = np.full((disks.num, 3), np.nan)
    for own_first in (True, False):
        for f in frames:
            todo = np.isnan(out[:, 0]) & (np.isin(owner, f.objects) == own_first)
            if not todo.any():
                continue
            uv, z = f.crop.camera.project(disks.means[todo].astype(np.float64))
            col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
            ok = (z > 0) & (col >= 0) & (col < f.crop.size) & (row >= 0) & (row < f.crop.size)
            ok[ok] &= (f.mask[row[ok], col[ok]] > 0) & (f.front_trans[row[ok], col[ok]] >= VISIBLE_TRANS)
            idx = np.flatnonzero(todo)[ok]
            out[idx] = f.target[row[ok], col[ok]]
    return out


def _colour_from_targets(run: _Run, disk_set: DiskSet, frames: list[targets.Frame], fills: list[_ObjectFill]
                         ) -> DiskSet:
    """The disks a target sees take its colour there (the others keep their neighbours' colour);
    records the fraction per object."""
    seen = _target_colours(disk_set.disks, disk_set.owner, frames)
    has = ~np.isnan(seen[:, 0])
    sh = disk_set.disks.sh.copy()
    sh[has, 0] = rgb_to_sh_dc(seen[has])
    for f in fills:
        run.records[f.id]["fill"]["target_coloured"] = round(float(has[disk_set.owner == f.id].mean()), 4)
    return dataclasses.replace(disk_set, disks=dataclasses.replace(disk_set.disks, sh=sh))


def _mark_filled(run: _Run, fills: list[_ObjectFill]) -> None:
    """Objects with a fill and no other status are "filled" when a target saw them, else "untargeted"."""
    for f in fills:
        rec = run.records[f.id]
        if rec["status"] is None:
            rec["status"] = "filled" if rec.get("primary_view") else "untargeted"


def _write(run: _Run, removed: np.ndarray, fill_data: GaussianSplatData | None) -> tuple[GaussianSplatData, int]:
    """Writes ``background.ply`` = (G0 \\ ∪R_i) ∪ G_fill; returns it and the number of kept Gaussians."""
    kept_out = run.data.subset(~removed)
    parts = [kept_out] + ([fill_data] if fill_data is not None and fill_data.num else [])
    background = GaussianSplatData.join(parts, like=run.data)
    write_gaussian_ply(run.out_dir / layout.BACKGROUND, background)
    return background, kept_out.num


def _section(run: _Run, config: BackgroundConfig, removed: np.ndarray, background: GaussianSplatData,
             kept_num: int, frames_record: list[dict], refine_record: dict | None) -> dict:
    """The manifest's ``background`` section (module docstring); objects not otherwise recorded are
    "removed"."""
    for rec in run.records.values():
        if rec["status"] is None:
            rec["status"] = "removed"
    return {
        "path": layout.BACKGROUND, "removed": int(removed.sum()), "filled": int(background.num - kept_num),
        "source_gaussians": int(run.data.num), "gaussians": int(background.num),
        "objects": [run.records[k] for k in sorted(run.records)], "unsupported_regions": run.unsupported,
        "failed_completions": run.failed,
        "targets": {"method": "external" if config.targets.external else config.targets.inpaint,
                    "folder": layout.BACKGROUND_TARGETS if config.targets.write and frames_record else None,
                    "frames": frames_record},
        "refine": refine_record, "renders": run.crops.renders, "render_launches": run.crops.launches,
        "config": to_dict(config)}


# --- targets ------------------------------------------------------------------------------------

def _wanted_views(run: _Run, fills: list[_ObjectFill], grid: float, external_folder: Path | None
                  ) -> tuple[list[tuple[int, list[int]]], set[int]]:
    """(view, objects whose disks its crop is centred on) per frame: each object's primary view,
    plus every view the editor's folder has a target for; and the set of those external views."""
    wanted: list[tuple[int, list[int]]] = []
    for f in fills:
        primary = targets.choose_primary(f.id, f.region.centres, f.region.plane.normal, run.cameras, grid)
        if primary is None:
            run.failed.append({"id": f.id, "reason": "no camera sees the fill region: coloured from neighbours only"})
            continue
        run.records[f.id]["primary_view"] = primary.as_dict(run.cameras)
        wanted.append((primary.view, [f.id]))
    external_frames = set()
    if external_folder is not None:
        for view in targets.external_views(external_folder, run.cameras):
            external_frames.add(view)
            if view not in {v for v, _ in wanted}:
                wanted.append((view, [f.id for f in fills]))
    return wanted, external_frames


def _shared_frames(boxes: list[tuple[int, list[int], np.ndarray]], external_frames: set[int], size: int,
                   margin: int) -> list[tuple[int, list[int], np.ndarray]]:
    """(view, objects, box) per frame: objects whose primary views coincide share one frame where
    the union of their boxes fits a crop of ``size`` at full resolution (the size every crop of the
    pass has anyway, so no other frame changes); an editor's frame stays as it is."""
    shared: list[tuple[int, list[int], np.ndarray]] = []
    for view, oids, box in boxes:
        for k, (v, others, b) in enumerate(shared):
            if v != view or view in external_frames:
                continue
            union = np.concatenate([np.minimum(b[:2], box[:2]), np.maximum(b[2:], box[2:])])
            if max(union[2] - union[0] + 1, union[3] - union[1] + 1) + 2 * margin <= size:
                shared[k] = (v, others + oids, union)
                break
        else:
            shared.append((view, list(oids), box))
    return shared


def _frames(run: _Run, removed: np.ndarray, disk_set: DiskSet, fills: list[_ObjectFill], config: BackgroundConfig
            ) -> tuple[list[targets.Frame], list[dict]]:
    """Primary views, the frame crops around their objects' disks (objects of one view share a crop
    where they fit one: ``_shared_frames``; plus external frames), the targets (written under
    ``background/targets`` when asked); returns the frames and their records. Every frame's renders
    are batched (``targets.render_plans``). removed: (N,) bool over G0."""
    external_folder = Path(config.targets.external) if config.targets.external else None
    wanted, external_frames = _wanted_views(run, fills, config.fill.grid, external_folder)
    cameras, data = run.cameras, run.data
    margin = config.crops.margin_px + config.targets.loss_ring_px + config.targets.region_dilate_px
    boxes = []
    for view, oids in wanted:
        box = targets.frame_box(cameras[view], disk_set.disks.subset(np.isin(disk_set.owner, oids)),
                                data.subset(np.zeros(0, np.int64)))
        if box is not None:
            boxes.append((view, oids, box))
    if not boxes:
        return [], []
    size = max(make_crop(cameras[v], v, b, config.crops.target_sizes, margin).size for v, _, b in boxes)
    boxes = _shared_frames(boxes, external_frames, size, margin)
    crops_of = [(oids, make_crop(cameras[v], v, b, (size,), margin)) for v, oids, b in boxes]  # one static size
    normals = disk_set.normals()
    footprints = CropFootprints.of(data)  # every frame culls the capture: its centres and scales read once
    tile = run.crops.renderer.config.tile_size
    plans = [targets.plan_frame(data, removed, disk_set.disks, normals, np.isin(disk_set.owner, oids), crop, oids,
                                np.zeros(3, np.float32), config, footprints, tile) for oids, crop in crops_of]
    frames = []
    for plan, images in zip(plans, targets.render_plans(plans, run.crops)):
        view = plan.crop.view
        try:
            if isinstance(images, RuntimeError):
                raise images
            external = (targets.read_external(external_folder, cameras[view])
                        if external_folder is not None and view in external_frames else None)
            frames.append(targets.finish_frame(plan, images, cameras[view], config, external))
        except RuntimeError as err:  # e.g. the renderer's buffers: these objects are untargeted
            for oid in plan.objects:
                run.records[oid].pop("primary_view", None)
                run.failed.append({"id": oid, "reason": f"target frame {cameras[view].name}: {err}"})
    if config.targets.write and frames:
        targets.write_targets(run.out_dir / layout.BACKGROUND_TARGETS, frames, cameras)
    return frames, [f.record(cameras) for f in frames]
