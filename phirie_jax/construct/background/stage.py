"""The background branch, end to end: ``run_background(scene_dir, out_dir, config)``.

Reads the capture G0 (the scene folder) and what the earlier stages wrote in ``out_dir``
(``manifest.json`` ``instances`` and ``objects``, ``observe/instance_<id>.npz``, the assets'
``objects/<id>/mesh.obj``), and for the objects being made movable:

1. removal, coupled to the object identity: R_i = R_obs ∪ R_asset ∪ R_mask (``construct.removal``);
2. per object a robust support plane and the exposed cells of it (``construct.fill``) — no plane
   is an *unsupported region*, recorded, and that object's hole stays;
3. inpainting targets: one primary view per object, all edits of a frame in one target
   (``construct.inpaint``; OpenCV Telea by default, Navier–Stokes, or an external editor's folder);
4. new disks on a ``grid`` lattice over the exposed cells plus a margin, coloured from the targets
   where a target sees them and from the neighbouring kept surface elsewhere, then refined — only
   they, the kept Gaussians fixed — against the targets (``construct.refine``, ``kernels.fill``).

Writes ``background.ply`` (INRIA format) = (G0 \\ ∪R_i) ∪ G_fill, ``background/targets/`` (the
targets, editor format), and the manifest ``background`` section: ``path``, ``removed``,
``filled`` (DESIGN.md "Contracts") and per object the counts of R_obs, R_asset, R_mask and their
union, the plane, the fill, the primary view and a status ("filled", "untargeted" — disks
coloured from neighbours only, no view sees them —, "nothing_exposed", "unsupported", "failed",
"skipped"), plus ``unsupported_regions``, ``failed_completions``, the frames, the refinement
record and the config; timings ``background`` and ``background.<step>``. A failure of one
object is recorded and the rest go on.
"""

from __future__ import annotations

import dataclasses
import time
import traceback
from pathlib import Path

import numpy as np

from phirie_jax.construct.background import plane as fill_mod
from phirie_jax.construct.background import targets as inpaint
from phirie_jax.construct.background.config import BackgroundConfig
from phirie_jax.construct.background.refine import DiskSet, refine
from phirie_jax.construct.background.removal import ObjectInput, load_object, removal_sets
from phirie_jax.construct.background.views import CropRenderer, cull, make_crop, pass_bucket
from phirie_jax.io.ply import write_gaussian_ply
from phirie_jax.io.scene import load_scene
from phirie_jax.manifest import Manifest, to_dict
from phirie_jax.types import Camera, GaussianSplatData, SceneInput

OUTPUT = "background.ply"
TARGETS = "background/targets"
SH_C0 = 0.28209479177387814
VISIBLE_TRANS = 0.5  # a target sees a disk where the front layer lets this much through
BASE_PERCENTILE = 2  # without a recorded support, an object's base is this percentile of Q_i's height


def _up(manifest: Manifest, scene: SceneInput) -> np.ndarray:
    up = ((manifest.get("construct") or {}).get("gravity") or {}).get("up")
    if up is not None:
        return np.asarray(up, np.float64) / np.linalg.norm(up)
    if scene.cameras:
        from phirie_jax.observe.auto import camera_up

        return camera_up(list(scene.cameras))
    return np.array([0.0, 0.0, 1.0])


def _base_height(manifest: Manifest, obj: ObjectInput, up: np.ndarray) -> float:
    for s in (manifest.get("construct") or {}).get("supports") or []:
        if s.get("id") == obj.id and s.get("height") is not None:
            return float(s["height"])
    return float(np.percentile(obj.q @ up, BASE_PERCENTILE))


@dataclasses.dataclass
class _Clock:
    seconds: dict = dataclasses.field(default_factory=dict)

    def add(self, step: str, since: float) -> float:
        now = time.perf_counter()
        self.seconds[f"background.{step}"] = self.seconds.get(f"background.{step}", 0.0) + now - since
        return now


def _fail(record: dict, status: str, reason: str, err: BaseException | None = None) -> None:
    record.update(status=status, reason=reason)
    if err is not None:
        record["traceback"] = traceback.format_exc(limit=4)


def _target_colours(disks: GaussianSplatData, owner: np.ndarray, frames: list[inpaint.Frame]) -> np.ndarray:
    """(N, 3) colour of each disk's pixel in the first frame that sees it (its own object's frames
    first), NaN where none does."""
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


def run_background(scene_dir: str | Path, out_dir: str | Path, config: BackgroundConfig | None = None,
                   scene: SceneInput | None = None) -> dict:
    """The background stage (module docstring). Returns the manifest as a dict."""
    out_dir = Path(out_dir)
    config = config or BackgroundConfig()
    manifest = Manifest.load_or_create(out_dir)
    objects = manifest.require("objects", "the object-construction stage")
    instances = {i["id"]: i for i in manifest.get("instances") or []}
    start = clock_t = time.perf_counter()
    clock = _Clock()
    scene = scene or load_scene(scene_dir, check_images=False)
    data = scene.require_gaussians()
    cameras = scene.require_cameras()
    up = _up(manifest, scene)
    crops = CropRenderer()

    records: dict[int, dict] = {}
    inputs: list[ObjectInput] = []
    for entry in objects:
        rec = records.setdefault(entry["id"], {"id": entry["id"], "status": None, "reason": None})
        if entry.get("status") not in config.remove_statuses:
            _fail(rec, "skipped", f"object status {entry.get('status')!r}: its Gaussians stay in the background")
            continue
        try:
            if entry["id"] not in instances:
                raise KeyError(f"no instance {entry['id']} in the manifest")
            inputs.append(load_object(entry, instances[entry["id"]], out_dir))
        except Exception as err:  # noqa: BLE001 — one object's failure is recorded, the scene goes on
            _fail(rec, "failed", f"inputs unreadable, not removed: {type(err).__name__}: {err}", err)
    clock_t = clock.add("load", clock_t)

    sets, removal_records = removal_sets(data, inputs, cameras, config, crops) if inputs else ([], [])
    removed = np.zeros(data.num, bool)
    for o, r_i, rec in zip(inputs, sets, removal_records):
        removed[r_i] = True
        records[o.id]["removed"] = rec
    clock_t = clock.add("removal", clock_t)

    kept = data.subset(~removed)
    kept_means = kept.means.astype(np.float64)
    kept_opacity = fill_mod.opacity(kept)
    kept_rgb = np.clip(kept.sh[:, 0].astype(np.float64) * SH_C0 + 0.5, 0, 1)
    unsupported, failed = [], []
    disk_parts, tangent_parts, owner_parts = [], [], []
    regions: dict[int, fill_mod.FillRegion] = {}
    for o, r_i in zip(inputs, sets):
        rec = records[o.id]
        try:
            obj_pts = fill_mod.object_points(o.q, o.mesh, config.grid, config.seed)
            base = _base_height(manifest, o, up)
            ring = fill_mod.ring_points(kept_means, kept_opacity, obj_pts, up, base, config)
            centre = o.q.mean(0)
            anchor = centre + (base - centre @ up) * up
            plane, reason = fill_mod.fit_plane(kept_means[ring], up, config, anchor)
            if plane is None:
                _fail(rec, "unsupported", reason)
                unsupported.append({"id": o.id, "reason": reason, "ring_points": len(ring),
                                    "removed": len(r_i)})
                continue
            rec["plane"] = plane.as_dict()
            region = fill_mod.fill_region(plane, kept_means, kept_opacity, obj_pts,
                                          data.means[r_i].astype(np.float64), config)
            rec["fill"] = {"exposed_cells": region.exposed, "disks": region.num,
                           "kept_spacing_m": round(region.covered_spacing, 5)}
            if region.num == 0:
                _fail(rec, "nothing_exposed", "the kept surface covers the whole footprint")
                continue
            if region.num > config.max_disks:
                reason = f"{region.num} disks exceed max_disks {config.max_disks}"
                _fail(rec, "failed", reason)
                failed.append({"id": o.id, "reason": reason})
                continue
            on_plane = np.abs(plane.height(kept_means)) <= config.slab
            colours = fill_mod.neighbour_colours(region.centres, kept_means[on_plane], kept_rgb[on_plane],
                                                 config.colour_neighbours)
            disk_parts.append(fill_mod.disks(region, colours, config, 1))
            tangent_parts.append(np.broadcast_to(np.stack([region.u, region.v]), (region.num, 2, 3)))
            owner_parts.append(np.full(region.num, o.id))
            regions[o.id] = region
        except Exception as err:  # noqa: BLE001
            reason = f"{type(err).__name__}: {err}"
            _fail(rec, "failed", reason, err)
            failed.append({"id": o.id, "reason": reason})
    clock_t = clock.add("plane", clock_t)

    fill_data, frames_record, refine_record = None, [], None
    if disk_parts:
        disk_set = DiskSet(GaussianSplatData.join(disk_parts, like=disk_parts[0]), np.concatenate(tangent_parts).astype(np.float32),
                           np.concatenate(owner_parts))
        frames, frames_record = _frames(data, removed, disk_set, regions, records, cameras, config, crops, out_dir,
                                        failed)
        clock_t = clock.add("targets", clock_t)
        if frames:
            seen = _target_colours(disk_set.disks, disk_set.owner, frames)
            has = ~np.isnan(seen[:, 0])
            sh = disk_set.disks.sh.copy()
            sh[has, 0] = (seen[has] - 0.5) / SH_C0
            disk_set = dataclasses.replace(disk_set, disks=dataclasses.replace(disk_set.disks, sh=sh))
            for oid in regions:
                own = disk_set.owner == oid
                records[oid]["fill"]["target_coloured"] = round(float(has[own].mean()), 4)
            if config.iterations > 0:
                fill_data, refine_record = refine(disk_set, frames, config, data.sh.shape[1])
            clock_t = clock.add("refine", clock_t)
        if fill_data is None:
            fill_data = disk_set.disks
        for oid in regions:
            rec = records[oid]
            if rec["status"] is None:
                rec["status"] = "filled" if rec.get("primary_view") else "untargeted"

    kept_out = data.subset(~removed)
    parts = [kept_out] + ([fill_data] if fill_data is not None and fill_data.num else [])
    background = GaussianSplatData.join(parts, like=data)
    write_gaussian_ply(out_dir / OUTPUT, background)
    clock.add("write", clock_t)
    for rec in records.values():
        if rec["status"] is None:
            rec["status"] = "removed"
    manifest.set("background", {
        "path": OUTPUT, "removed": int(removed.sum()), "filled": int(background.num - kept_out.num),
        "source_gaussians": int(data.num), "gaussians": int(background.num),
        "objects": [records[k] for k in sorted(records)], "unsupported_regions": unsupported,
        "failed_completions": failed,
        "targets": {"method": "external" if config.targets else config.inpaint,
                    "folder": TARGETS if config.write_targets and frames_record else None,
                    "frames": frames_record},
        "refine": refine_record, "renders": crops.renders, "config": to_dict(config)})
    for step, seconds in clock.seconds.items():
        manifest.record_timing(step, seconds)
    manifest.record_timing("background", time.perf_counter() - start)
    manifest.write()
    return manifest.data


def _frames(data: GaussianSplatData, removed: np.ndarray, disk_set: DiskSet, regions: dict, records: dict,
            cameras: tuple[Camera, ...], config: BackgroundConfig, crops: CropRenderer, out_dir: Path,
            failed: list) -> tuple[list[inpaint.Frame], list[dict]]:
    """Primary views, one frame crop per object around its disks (plus external frames), the targets."""
    wanted: list[tuple[int, list[int]]] = []  # (view, objects whose disks the crop is centred on)
    for oid, region in regions.items():
        primary = inpaint.choose_primary(oid, region.centres, region.plane.normal, cameras, config.grid)
        if primary is None:
            failed.append({"id": oid, "reason": "no camera sees the fill region: coloured from neighbours only"})
            continue
        records[oid]["primary_view"] = primary.as_dict(cameras)
        wanted.append((primary.view, [oid]))
    external_folder = Path(config.targets) if config.targets else None
    external_frames = set()
    if external_folder is not None:
        for view in inpaint.external_views(external_folder, cameras):
            external_frames.add(view)
            if view not in {v for v, _ in wanted}:
                wanted.append((view, list(regions)))
    margin = config.crop_margin_px + config.loss_ring_px + config.region_dilate_px
    boxes = []
    for view, oids in wanted:
        box = inpaint.frame_box(cameras[view], disk_set.disks.subset(np.isin(disk_set.owner, oids)),
                                data.subset(np.zeros(0, np.int64)))
        if box is not None:
            boxes.append((view, oids, box))
    if not boxes:
        return [], []
    size = max(make_crop(cameras[v], v, b, config.crop_sizes, margin).size for v, _, b in boxes)
    crops_of = [(oids, make_crop(cameras[v], v, b, (size,), margin)) for v, oids, b in boxes]  # one static size
    pad = pass_bucket([len(cull(data, c.camera)) for _, c in crops_of])
    frames = []
    for oids, crop in crops_of:
        view = crop.view
        try:
            external = (inpaint.read_external(external_folder, cameras[view])
                        if external_folder is not None and view in external_frames else None)
            frames.append(inpaint.build_frame(data, removed, disk_set.disks, disk_set.normals(),
                                              np.isin(disk_set.owner, oids), crop, oids, cameras[view],
                                              np.zeros(3, np.float32), config, crops, pad, external))
        except RuntimeError as err:  # e.g. the renderer's buffers: these objects are untargeted
            for oid in oids:
                records[oid].pop("primary_view", None)
                failed.append({"id": oid, "reason": f"target frame {cameras[view].name}: {err}"})
    if config.write_targets and frames:
        inpaint.write_targets(out_dir / TARGETS, frames, cameras)
    return frames, [f.record(cameras) for f in frames]
