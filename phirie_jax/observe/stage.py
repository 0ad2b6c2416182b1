"""Scene Observation, end to end: ``observe(scene_dir, out_dir, config, masks, scene, prompts, frame)``
(``run_observe(scene_dir, out_dir, ...)`` on an output folder alone).

Outputs (paths relative to ``out_dir``):

- returned, the manifest's sections: ``instances`` (``records.InstanceRecord``;
  docs/architecture.md "Contracts": ``id``, ``category``, ``views`` = supporting camera indices, ``num_points``, ``bounds``, ``source``; plus ``points``,
  ``confidence``, ``view_names``, ``support`` (``observe.support``: height in the gravity
  frame, source, hits, normal), ``points_dropped`` (by reason)), ``observe`` (surface used and how it was made, mask
  source, failed views, rejected proposals and clusters, the config) and
  ``timings`` (``observe`` and ``observe.<step>`` in seconds).
- ``observe/instance_<id>.npz``, one per instance:
  ``points`` (N, 3) float32 observed surface samples Q_i (one per ``points_voxel``; only
  points whose association voxel is seen by ≥ ``min_views`` of the instance's views and
  that lie inside the instance's silhouette in ≥ ``silhouette_agreement`` of the views that
  judge them, and not within ``support_clearance`` of the support found under them),
  and per supporting proposal (V rows): ``views`` (V,) int32 camera index, ``labels`` (V,)
  int64 value of the instance in that view's mask, ``mask_paths`` (V,) str mask image,
  ``pixels`` (V,) int64 mask area, ``bboxes`` (V, 4) int32 x0 y0 x1 y1 (inclusive),
  ``lifted`` (V,) int32 points lifted from that view.
- ``observe/masks/<image stem>.png``: the per-view masks when they were made here
  (``auto``, ``prompts``), 16-bit instance ids like mask files.
- ``observe/prompts.npz``: with prompts, the scene's Gaussians each prompt took
  (``observe.prompt_lift.PROMPT_RECORD``).
- ``observe/surface.ply``: the splat-derived surface, when one was built.
"""

from __future__ import annotations

import dataclasses
import io
import time
from collections import Counter
from pathlib import Path

import numpy as np

from phirie_jax.errors import SceneInputError
from phirie_jax.frame.gravity import gravity_frame
from phirie_jax.io.atomic import write_bytes
from phirie_jax.io.scene import load_scene
from phirie_jax.manifest import Manifest, Timings, to_dict
from phirie_jax.observe import auto as auto_mod
from phirie_jax.observe.associate import associate
from phirie_jax.observe.config import ObserveConfig
from phirie_jax.observe.floaters import surface_gaussians
from phirie_jax.observe.lift import Proposal, lift_view
from phirie_jax.observe.masks import (
    ViewFailure,
    camera_problem,
    external_masks,
    file_masks,
    projected_masks,
    scannetpp_vertex_labels,
)
from phirie_jax.observe.raycast import Raycaster
from phirie_jax.observe.support import Support, Wall, find_support
from phirie_jax.observe.support_fit import frame_support_plane
from phirie_jax.observe.surface import SurfaceMesh, fuse_depths, snap_to_centres
from phirie_jax.records import FrameRecord, InstanceRecord, plain
from phirie_jax.types import Camera, SceneInput


def working_camera(camera: Camera, working_width: int) -> Camera:
    """The camera scaled down to ``working_width`` when its photo is wider (0: as it is)."""
    if working_width <= 0 or camera.width <= working_width:
        return camera
    return camera.scaled(working_width / camera.width)


def render_depths(scene: SceneInput, config: ObserveConfig, gaussians=None, shared=None
                  ) -> tuple[list[np.ndarray], list[Camera], list[dict]]:
    """Rendered depth (alpha ≥ min_alpha, else 0) at every ``view_stride``-th camera, and failures.

    Each camera is rendered at ``config.working_width`` (``working_camera``); the returned
    cameras are the ones rendered. ``gaussians``: the host Gaussians to render (default the
    scene's). ``shared``: another user of the same renders (prompt masks,
    ``observe.prompt_lift.PromptMasks``): its ``features`` (N, F) ride along and ``take(view,
    output)`` sees each render."""
    from phirie_jax.render import prepared, render

    gaussians = prepared((gaussians if gaussians is not None else scene.require_gaussians()).to_host_kernel())
    depths, cams, failures = [], [], []
    for view in range(0, len(scene.cameras), config.surface.view_stride):
        cam = scene.cameras[view]
        problem = camera_problem(cam)
        if problem is None:
            cam = working_camera(cam, config.working_width)
            try:
                out = render(gaussians, cam, features=None if shared is None else shared.features)
            except RuntimeError as err:  # e.g. the scene does not fit the renderer's buffers
                problem = f"render failed: {err}"
        if problem:
            failures.append({"view": view, "path": cam.name, "reason": problem})
            continue
        if shared is not None:
            shared.take(view, out)
        alpha = np.asarray(out.alpha)
        depths.append(np.where(alpha >= config.surface.min_alpha, np.asarray(out.depth_normalized), 0.0))
        cams.append(cam)
    return depths, cams, failures


def scene_surface(scene: SceneInput, config: ObserveConfig, out_dir: Path, shared=None) -> tuple[SurfaceMesh, dict]:
    """The surface to lift onto, and a record of where it came from.

    A splat-derived surface is fused from the depth of the Gaussians that pass the floater
    rules (``observe/floaters.py``; counts in the record's ``floaters``) and snapped onto
    their opaque centres. Raises ``SurfaceTooLargeError`` when its grid would exceed the
    memory budget."""
    import trimesh

    use_mesh = config.surface_source == "mesh" or (config.surface_source == "auto" and scene.surface_mesh)
    if use_mesh:
        if scene.surface_mesh is None:
            raise SceneInputError(scene.root, "surface", "no scan mesh (expected --surface PATH, surface.ply, "
                                  "mesh.ply or scans/mesh_aligned_0.05.ply) and surface_source is 'mesh'")
        try:
            mesh = trimesh.load(scene.surface_mesh, force="mesh", process=False)
        except (ValueError, OSError, KeyError, IndexError, TypeError) as err:  # what trimesh raises for bad files
            raise SceneInputError(scene.surface_mesh, None, f"not a readable mesh ({err})") from None
        if len(mesh.faces) == 0:
            raise SceneInputError(scene.surface_mesh, "faces", "none (expected a triangle mesh)")
        record = {"kind": "scan", "path": str(scene.surface_mesh), "faces": len(mesh.faces)}
        surface = SurfaceMesh(scene.to_world(mesh.vertices), np.asarray(mesh.faces, np.int64), record)
        if scene.capture_to_world is not None:  # later stages read the surface in the scene's frame
            write_bytes(out_dir / "observe" / "surface.ply", surface.to_trimesh().export(file_type="ply"))
            record = {**record, "path": "observe/surface.ply", "scan": str(scene.surface_mesh)}
        return surface, record
    if scene.gaussians is None or not scene.cameras:
        raise SceneInputError(scene.root, "surface", "no scan mesh and no way to build one (a splat-derived "
                              "surface needs the Gaussians and posed cameras; expected --surface PATH or "
                              "surface.ply, else point_cloud.ply with sparse/0/ or transforms.json)")
    g, floaters = surface_gaussians(scene.gaussians, config.surface.floaters)
    if g.num == 0:
        raise SceneInputError(scene.root, "surface", f"every Gaussian was left out as a floater ({floaters}); "
                              "expected some opaque ones (see observe.surface.floaters)")
    t0 = time.perf_counter()
    shared = shared if shared is not None and shared.renders(g) else None
    depths, cams, failures = render_depths(scene, config, g, shared)
    render_s = time.perf_counter() - t0
    if not depths:
        raise SceneInputError(scene.root, "surface", "no view could be rendered to build a splat-derived surface")
    surface = fuse_depths(depths, cams, config.surface)
    if config.surface.snap_radius > 0:
        t0 = time.perf_counter()
        opaque = 1.0 / (1.0 + np.exp(-g.opacity_logits.astype(np.float64))) >= config.surface.snap_min_opacity
        vertices, offset = snap_to_centres(surface.vertices, surface.faces, g.means[opaque].astype(np.float64),
                                           config.surface.snap_radius, config.surface.snap_neighbours)
        info = {**surface.info, "snap_s": time.perf_counter() - t0,
                "snap_offset_mm_median": float(np.median(offset) * 1000),
                "snap_offset_mm_p95_abs": float(np.percentile(np.abs(offset), 95) * 1000)}
        surface = SurfaceMesh(vertices, surface.faces, info)
    data = surface.to_trimesh().export(file_type="ply")
    write_bytes(out_dir / "observe" / "surface.ply", data)
    record = {"kind": "splats", "path": "observe/surface.ply", "render_s": round(render_s, 4),
              "render_size": [cams[0].width, cams[0].height], "failed_views": failures, "floaters": floaters,
              **{k: (round(v, 4) if isinstance(v, float) else v) for k, v in surface.info.items()}}
    return surface, record


def mask_views(scene: SceneInput, masks: str | Path, raycaster: Raycaster,
               config: ObserveConfig, record: dict, up: np.ndarray | None = None, frame_record: dict | None = None,
               prompt_masks=None):
    """The per-view masks of the chosen source (an iterator) and the source's name; ``up`` (3,)
    is the scene's (automatic masks look for supports under it; default +z) and ``frame_record``
    the manifest's ``frame`` (its support plane seeds automatic discovery's). ``masks`` "prompts":
    ``prompt_masks``, the prompts lifted to objects (``observe.prompt_lift.PromptMasks``)."""
    if masks == "prompts":
        return prompt_masks.views(), "prompts"
    if masks == "files":
        if scene.masks is not None:
            return file_masks(scene.cameras, scene.masks), "files"
        if scene.segments_anno is not None and scene.surface_mesh is not None:
            # the annotations label the scan's vertices: project that mesh, whatever surface is lifted onto
            import trimesh

            scan = trimesh.load(scene.surface_mesh, force="mesh", process=False)
            vertex_labels, names = scannetpp_vertex_labels(scene.segments_anno, len(scan.vertices))
            record["annotations"] = str(scene.segments_anno)
            return projected_masks(Raycaster(scene.to_world(scan.vertices), scan.faces, config.working_width),
                                   vertex_labels, scene.cameras, names,
                                   "segments_anno"), "files"
        raise SceneInputError(scene.root / "masks", "--masks files",
                              "no masks/ folder and no ScanNet++ annotations (use --masks auto or a folder)")
    if masks == "auto":
        t0 = time.perf_counter()
        cams = [c for c in scene.cameras if camera_problem(c) is None]
        samples = auto_mod.observed_samples(raycaster, cams, config.auto.sample_stride, config.auto.sample_voxel)
        seed = frame_support_plane(frame_record)
        uncertainty = float((frame_record or {}).get("scale_uncertainty") or 1.0)
        seg = auto_mod.segment(samples, np.array([0.0, 0.0, 1.0]) if up is None else up, config.auto, cams,
                               raycaster, seeds=() if seed is None else (seed,),
                               scale_uncertainty=max(1.0, uncertainty))
        record["auto"] = {"samples": len(samples.points), "up": seg.up.round(6).tolist(),
                          "frame_support": None if seed is None else {"normal": seed[0].round(6).tolist(),
                                                                      "offset": round(seed[1], 6)},
                          "supports": [s.as_dict() for s in seg.supports], "support_planes": seg.planes,
                          "objects": seg.objects, "rejected_clusters": seg.rejected,
                          "segment_s": round(time.perf_counter() - t0, 4)}
        return auto_mod.auto_masks(raycaster, scene.cameras, seg, config.auto.sample_voxel), "auto"
    return external_masks(Path(masks), scene.cameras), "external"


def _write_mask(out_dir: Path, camera: Camera, labels: np.ndarray) -> str:
    import cv2

    rel = f"observe/masks/{Path(camera.name).stem}.png"
    ok, buf = cv2.imencode(".png", labels.astype(np.uint16))
    if not ok:
        raise RuntimeError(f"PNG encoding failed for {rel}")
    write_bytes(out_dir / rel, buf.tobytes())
    return rel


def instance_points(instance_id: int, members: list[Proposal], config: ObserveConfig) -> tuple[np.ndarray, int]:
    """(Q_i before the silhouette check, points dropped as seen from one view only).

    A point counts when its association voxel is seen by ≥ ``min_views`` of the instance's
    views (a ray grazing a silhouette lands on the table behind in one view, never in the same
    place twice); the rest are thinned to one per ``points_voxel`` and capped at ``max_points``."""
    from phirie_jax.observe.surface import pack_keys

    points = np.concatenate([p.points for p in members])
    voxel_keys = pack_keys(np.floor(points / config.voxel))
    owner = np.repeat(np.array([p.view for p in members]), [len(p.points) for p in members])
    pairs = np.unique(np.stack([voxel_keys, owner], 1), axis=0)
    keys, views_per_key = np.unique(pairs[:, 0], return_counts=True)
    seen = views_per_key[np.searchsorted(keys, voxel_keys)] >= config.min_views
    points = points[seen]
    _, first = np.unique(pack_keys(np.floor(points / config.points_voxel)), return_index=True)
    points = points[np.sort(first)]
    if len(points) > config.max_points:
        keep = np.random.default_rng(instance_id).choice(len(points), config.max_points, replace=False)
        points = points[np.sort(keep)]
    return points, int((~seen).sum())


def silhouette_agreement(points: list[np.ndarray], members: list[list[Proposal]], mask_paths: dict[int, str],
                         cameras: tuple[Camera, ...], out_dir: Path) -> list[np.ndarray]:
    """Per instance, (P_k,) the fraction of its counted views that show each point on its label
    (``ObserveConfig.silhouette_agreement``; NaN: no view counted it). One pass over the views:
    each mask is read once for every instance that has a proposal there."""
    from phirie_jax.layout import resolve
    from phirie_jax.observe.lift import silhouette_votes
    from phirie_jax.observe.masks import read_label_png

    inside = [np.zeros(len(p)) for p in points]
    counted = [np.zeros(len(p)) for p in points]
    by_view: dict[int, list[tuple[int, int]]] = {}
    for k, group in enumerate(members):
        for p in group:
            by_view.setdefault(p.view, []).append((k, p.label))
    for view, entries in sorted(by_view.items()):
        if view not in mask_paths:
            continue
        try:
            labels = read_label_png(resolve(out_dir, mask_paths[view]), cameras[view])
        except (SceneInputError, OSError):
            continue
        ks = [k for k, _ in entries]
        for k, (on, seen) in zip(ks, silhouette_votes([points[k] for k in ks], [lab for _, lab in entries],
                                                      cameras[view], labels)):
            inside[k] += on
            counted[k] += seen
    with np.errstate(invalid="ignore", divide="ignore"):
        return [np.where(c > 0, i / np.maximum(c, 1), np.nan) for i, c in zip(inside, counted)]


def instance_record(instance_id: int, members: list[Proposal], points: np.ndarray, support: Support,
                    dropped: dict[str, int], mask_paths: dict[int, str], cameras: tuple[Camera, ...], source: str,
                    out_dir: Path, wall: Wall | None = None) -> dict:
    """The manifest entry of one instance of Q_i ``points`` standing on ``support`` (writes its
    .npz), in front of ``wall`` when one was found behind it; ``dropped``: the points left out,
    by reason."""
    if len(points) == 0:
        raise ValueError(f"no observed point of instance {instance_id} agrees with its masks ({dropped})")
    views = sorted({p.view for p in members})
    centre = points.mean(0)
    visible = 0
    for cam in cameras:
        if camera_problem(cam) is None:
            uv, depth = cam.project(centre[None])
            visible += bool(depth[0] > 0 and 0 <= uv[0, 0] < cam.width and 0 <= uv[0, 1] < cam.height)
    scores = [1.0 if p.score is None else p.score for p in members]
    confidence = float(np.mean(scores)) * min(1.0, len(views) / max(visible, 1))
    votes = Counter()
    for p, s in zip(members, scores):
        if p.category:
            votes[p.category] += s
    rel = f"observe/instance_{instance_id}.npz"
    buf = io.BytesIO()
    np.savez_compressed(
        buf, points=points.astype(np.float32), views=np.array([p.view for p in members], np.int32),
        labels=np.array([p.label for p in members], np.int64),
        mask_paths=np.array([mask_paths.get(p.view, "") for p in members], dtype=str),
        pixels=np.array([p.pixels for p in members], np.int64),
        bboxes=np.array([p.bbox for p in members], np.int32).reshape(-1, 4),
        lifted=np.array([len(p.points) for p in members], np.int32))
    write_bytes(out_dir / rel, buf.getvalue())
    return {"id": int(instance_id), "category": votes.most_common(1)[0][0] if votes else None,
            "views": views, "view_names": [cameras[v].name for v in views], "num_points": len(points),
            "bounds": [points.min(0).round(6).tolist(), points.max(0).round(6).tolist()],
            "source": source, "points": rel, "confidence": round(confidence, 4),
            "support": support.as_record(), "points_dropped": dropped,
            **({"wall": wall.as_record()} if wall is not None else {})}


@dataclasses.dataclass
class _Lifted:
    proposals: list[Proposal] = dataclasses.field(default_factory=list)
    rejected: list[dict] = dataclasses.field(default_factory=list)   # proposals left out, with the reason
    failures: list[dict] = dataclasses.field(default_factory=list)   # views that gave no masks
    mask_paths: dict[int, str] = dataclasses.field(default_factory=dict)  # view → its mask file


def _lift_views(views, source: str, cameras: tuple[Camera, ...], raycaster: Raycaster, config: ObserveConfig,
                out_dir: Path, timings: Timings) -> _Lifted:
    """Each view's masks (made as they are asked for) lifted onto the surface; timings
    ``observe.masks`` and ``observe.lift``."""
    lifted, iterator = _Lifted(), iter(views)
    while True:
        with timings.timed("observe.masks"):
            item = next(iterator, None)
        if item is None:
            return lifted
        if isinstance(item, ViewFailure):
            lifted.failures.append(item.as_dict())
            continue
        with timings.timed("observe.lift"):
            lifted.mask_paths[item.view] = (_write_mask(out_dir, cameras[item.view], item.labels)
                                            if source in ("auto", "prompts") else item.path)
            found, dropped = lift_view(raycaster, cameras[item.view], item, config)
        lifted.proposals += found
        lifted.rejected += dropped


def _instances(lifted: _Lifted, cameras: tuple[Camera, ...], source: str, config: ObserveConfig, out_dir: Path,
               timings: Timings, up: np.ndarray, raycaster: Raycaster, supports: dict[int, Support] | None = None,
               walls: dict[int, Wall] | None = None) -> tuple[list[dict], list[dict], list[dict]]:
    """Voxel association of the lifted proposals → (instance records, failed instances, rejected);
    ``walls``: instance id → the wall found behind it (prompts)."""
    with timings.timed("observe.associate"):
        assoc = associate(lifted.proposals, config.voxel, config.overlap, config.min_views)
    groups = [(instance_id, [lifted.proposals[i] for i in idx]) for instance_id, idx in assoc.groups]
    with timings.timed("observe.consistency"):
        kept = _consistent_points(groups, lifted.mask_paths, cameras, config, out_dir, up, raycaster, supports)
    instances, failed = [], []
    rejected = [{k: v for k, v in r.items() if k != "proposal"} for r in assoc.rejected]
    with timings.timed("observe.write"):
        for (instance_id, members), (points, support, dropped) in zip(groups, kept):
            try:
                record = instance_record(instance_id, members, points, support, dropped, lifted.mask_paths,
                                         cameras, source, out_dir, (walls or {}).get(instance_id))
            except (OSError, ValueError) as err:
                failed.append({"id": instance_id, "reason": f"{type(err).__name__}: {err}"})
                continue
            reason = _seen_too_little(record, config) if source == "auto" else None
            if reason:
                (out_dir / record["points"]).unlink(missing_ok=True)
                rejected.append({"instance": instance_id, "views": len(record["views"]),
                                 "confidence": record["confidence"], "reason": reason})
                continue
            instances.append(record)
    return instances, failed, rejected


def _seen_too_little(record: dict, config: ObserveConfig) -> str | None:
    """Why an automatically discovered instance is not one: supported by fewer than ``auto.min_views``
    views, or by less than ``auto.min_view_fraction`` of the views that have it in the image (its
    ``confidence``: no score backs an automatic mask). None when it was seen enough."""
    views, share = len(record["views"]), record["confidence"]
    if views < config.auto.min_views:
        return f"supported by {views} views (< auto.min_views {config.auto.min_views})"
    if share < config.auto.min_view_fraction:
        return (f"supported by {views} views, {share:.2f} of those that have it in the image "
                f"(< auto.min_view_fraction {config.auto.min_view_fraction})")
    return None


def _consistent_points(groups: list[tuple[int, list[Proposal]]], mask_paths: dict[int, str],
                       cameras: tuple[Camera, ...], config: ObserveConfig, out_dir: Path, up: np.ndarray,
                       raycaster: Raycaster, supports: dict[int, Support] | None = None
                       ) -> list[tuple[np.ndarray, Support, dict]]:
    """Per instance (Q_i, its support, points dropped by reason): the lifted points seen from ≥
    ``min_views`` views, inside the instance's silhouette in ≥ ``silhouette_agreement`` of the
    views that judge them, and not on the support found under them (``supports``: an instance's
    support found before, e.g. under a prompt's object; else ``observe.support.find_support``)."""
    frame = gravity_frame(up, "scene frame")
    thinned = [instance_points(instance_id, members, config) for instance_id, members in groups]
    agreement = (silhouette_agreement([p for p, _ in thinned], [m for _, m in groups], mask_paths, cameras, out_dir)
                 if config.silhouette_agreement > 0 else [np.full(len(p), np.nan) for p, _ in thinned])
    kept = []
    for (instance_id, _), (points, single_view), agree in zip(groups, thinned, agreement):
        inside = ~(agree < config.silhouette_agreement)  # NaN (no view judged it) keeps the point
        points = points[inside]
        support = (supports or {}).get(instance_id) or find_support(frame.to_gravity(points), frame, raycaster)
        off_support = np.ones(len(points), bool)
        if support.is_plane and config.support_clearance is not None:
            off_support = frame.to_gravity(points)[:, 2] >= support.height + config.support_clearance
            support = dataclasses.replace(support, clearance=config.support_clearance)
        kept.append((points[off_support], support,
                     {"single_view": single_view, "outside_silhouette": int((~inside).sum()),
                      "on_support": int((~off_support).sum())}))
    return kept


def run_observe(scene_dir: str | Path, out_dir: str | Path, config: ObserveConfig | None = None,
                masks: str | Path | None = None, scene: SceneInput | None = None, prompts=()) -> dict:
    """The observation stage on an output folder alone (``observe``; the folder's manifest read
    and written): returns the manifest as a dict."""
    manifest = Manifest.load_or_create(out_dir)
    instances, record = observe(scene_dir, out_dir, config, masks, scene, prompts, manifest.frame(), manifest.timings)
    manifest.set("instances", instances)
    manifest.set("observe", record)
    manifest.write()
    return manifest.data


def observe(scene_dir: str | Path, out_dir: str | Path, config: ObserveConfig | None = None,
            masks: str | Path | None = None, scene: SceneInput | None = None, prompts=(),
            frame: FrameRecord | None = None, timings: Timings | None = None
            ) -> tuple[tuple[InstanceRecord, ...], dict]:
    """Run Scene Observation on a scene (``scene``, else the folder ``scene_dir``) in the world of
    ``frame`` (the frame stage's record; None: +z up); writes its files in ``out_dir`` (see the
    module docstring) and returns (the instances, the ``observe`` record).

    masks: "files" (mask PNGs or ScanNet++ annotations), "auto", or a folder of an external
    segmenter's per-image PNG + JSON; None = "files" when the scene has masks, else "auto".
    prompts: checked prompts (``observe.prompts.Prompt``; with masks None) make the masks:
    prompt k is instance k. timings: where the steps' times go (``observe``, ``observe.<step>``).
    Raises ``SceneInputError`` for unusable input as a whole; a failing view or instance is
    recorded and the rest goes on.
    """
    out_dir = Path(out_dir)
    config = config or ObserveConfig()
    timings = timings if timings is not None else Timings()
    up = frame.up_vector() if frame is not None else np.array([0.0, 0.0, 1.0])
    with timings.timed("observe"):
        scene = scene or load_scene(scene_dir)
        cameras = scene.require_cameras()
        if prompts:
            if masks is not None:
                raise ValueError(f"prompts and masks {masks!r}: expected one mask source")
            masks = "prompts"
        if masks is None:
            masks = "files" if (scene.masks is not None or scene.segments_anno is not None) else "auto"
        record: dict = {}
        prompt_masks = None
        if masks == "prompts":
            from phirie_jax.observe.prompt_masks import PromptMasks

            with timings.timed("observe.prompts"):
                prompt_masks = PromptMasks.lift(scene, prompts, config, record, out_dir)
        with timings.timed("observe.surface"):
            surface, surface_record = scene_surface(scene, config, out_dir, prompt_masks)
            raycaster = Raycaster(surface.vertices, surface.faces, config.working_width)
        record["surface"] = surface_record
        with timings.timed("observe.masks"):
            views, source = mask_views(scene, masks, raycaster, config, record, up,
                                       None if frame is None else frame.to_json(), prompt_masks)
        lifted = _lift_views(views, source, cameras, raycaster, config, out_dir, timings)
        instances, failed, rejected = _instances(lifted, cameras, source, config, out_dir, timings, up, raycaster,
                                                 prompt_masks.supports() if prompt_masks is not None else None,
                                                 prompt_masks.walls() if prompt_masks is not None else None)
        record.update(masks={"source": source, "path": None if source != "external" else str(masks),
                             "failed_views": lifted.failures},
                      proposals=len(lifted.proposals), rejected_proposals=lifted.rejected + rejected,
                      failed_instances=failed, config=to_dict(config))
    return tuple(InstanceRecord.from_json(plain(i)) for i in instances), plain(record)
