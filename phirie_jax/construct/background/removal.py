"""Source-Gaussian removal coupled to the object identity: R_i = R_obs ∪ R_asset ∪ R_mask ∪ R_enclosed ∪ R_reach.

For each object the object stage made (status in ``RemovalConfig.statuses``):

- R_obs: Gaussians whose centre is within ``obs_radius`` (paper: 3 cm) of the observed
  surface samples Q_i (``observe/instance_<id>.npz``);
- R_asset: ... within ``asset_radius`` (paper: 2.4 cm) of the registered asset's surface
  (``objects/<id>/mesh.obj`` placed by ``pose``): it reaches what the scan missed (the back,
  the base); and (ours) every centre inside the placed asset: optimizer-shaped captures put
  Gaussians deep inside large objects, beyond the paper's shell, and they would stay as
  coloured remains where the object stood;
- R_mask: centres inside the expanded object bounds (Q_i ∪ the placed asset, grown by
  ``bounds_margin``) that project inside the instance's mask in ≥ ``mask_votes`` views (paper: 2)
  *and are visible there*: a centre more than ``occlusion_tolerance`` behind the depth rendered at
  its pixel is occluded in that view and does not vote (the paper's code has no such test, so
  the table behind an object, inside its bounds, was voted away). The depth is rendered from the
  Gaussians inside the expanded bounds only: a mask pixel is the *first* hit's label, so what
  is in front of the instance there is the instance itself, which lies inside its bounds.

- R_enclosed (ours): the remaining Gaussians of the expanded bounds walled in by the placed asset
  (horizontal rays in 8 directions all meet it, from the centre or up to 1 cm above it): the inside of an open container — a mug's inner
  floor — is neither near its outer surface nor inside its volume, and stayed as a coloured disc
  where the mug stood;
- R_reach (ours): the remaining Gaussians of the expanded bounds whose longest axis, 2 σ either
  side of the centre, ends more than 5 mm inside the placed asset: optimizer-shaped needles that
  cross the object/support contact with their centre on the support, hidden in the capture where
  they enter the object and a streak on the support once it moves.

Objects the object stage rejected or failed are not removed (they have no body; their
Gaussians stay in the background) and are recorded as skipped.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np

from phirie_jax.construct.background.config import BackgroundConfig
from phirie_jax.construct.background.plane import BoxIndex, tangent_basis
from phirie_jax.construct.background.views import (
    Crop,
    CropImage,
    CropJob,
    CropRenderer,
    batch_size,
    colourless,
    make_crop,
    pass_bucket,
)
from phirie_jax.io.mesh import read_mesh
from phirie_jax.io.ply import read_gaussian_ply
from phirie_jax.layout import resolve
from phirie_jax.observe.raycast import Raycaster
from phirie_jax.records import InstanceRecord, ObjectRecord
from phirie_jax.threads import query_workers
from phirie_jax.types import Camera, GaussianSplatData

DEPTH_ALPHA = 0.5  # rendered alpha below this at a pixel: nothing of the object there to occlude
OWN_GAUSSIAN = 1e-5  # metres: a capture Gaussian this close to one of the object's visual Gaussians is that one


@dataclasses.dataclass
class ObjectInput:
    """What the background branch knows of one object."""

    id: int
    q: np.ndarray                          # (M, 3) observed surface samples Q_i
    mesh: tuple[np.ndarray, np.ndarray] | None  # placed asset (world vertices (V, 3), faces (F, 3))
    views: np.ndarray                      # (V,) camera index of each mask view
    labels: np.ndarray                     # (V,) the instance's value in that view's mask
    mask_paths: list[Path]                 # (V,) mask image of that view
    bboxes: np.ndarray                     # (V, 4) x0 y0 x1 y1 of the instance in that mask
    pixels: np.ndarray                     # (V,) mask area
    visual_means: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))  # (G, 3) its
    # visual Gaussians' centres placed in the scene: the captured ones are the capture's own

    def bounds(self, margin: float) -> np.ndarray:
        """(2, 3) Q_i ∪ asset box grown by ``margin``."""
        pts = self.q if self.mesh is None else np.concatenate([self.q, self.mesh[0]])
        return np.stack([pts.min(0) - margin, pts.max(0) + margin])


def load_object(entry: ObjectRecord, instance: InstanceRecord, out_dir: Path) -> ObjectInput:
    """An object's inputs from its record and its instance's."""
    data = np.load(resolve(out_dir, instance.points))
    mesh = None
    if entry.mesh and entry.pose is not None:
        vertices, faces = read_mesh(resolve(out_dir, entry.mesh))
        pose = np.asarray(entry.pose, np.float64)
        mesh = (vertices @ pose[:3, :3].T + pose[:3, 3], faces)
    visual = np.zeros((0, 3))
    if entry.visual and entry.pose is not None:
        pose = np.asarray(entry.pose, np.float64)
        visual = read_gaussian_ply(resolve(out_dir, entry.visual)).means.astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
    return ObjectInput(
        id=int(entry.id), q=np.asarray(data["points"], np.float64), mesh=mesh,
        views=np.asarray(data["views"], np.int64), labels=np.asarray(data["labels"], np.int64),
        mask_paths=[resolve(out_dir, str(p)) for p in data["mask_paths"]],
        bboxes=np.asarray(data["bboxes"], np.int64).reshape(-1, 4), pixels=np.asarray(data["pixels"], np.int64),
        visual_means=visual)


def _in_box(means: np.ndarray, box: np.ndarray, index: BoxIndex | None = None) -> np.ndarray:
    """Sorted indices of ``means`` (N, 3) inside the closed ``box`` (2, 3); index: ``BoxIndex(means)``
    (the same indices, reading only the box's x-slab)."""
    if index is not None:
        return index.within(box[0], box[1])
    return np.flatnonzero(np.all((means >= box[0]) & (means <= box[1]), axis=1))


def near_points(means: np.ndarray, points: np.ndarray, radius: float, index: BoxIndex | None = None) -> np.ndarray:
    """Indices of ``means`` within ``radius`` of any of ``points`` (R_obs); index: ``BoxIndex(means)``."""
    from scipy.spatial import cKDTree

    if len(points) == 0:
        return np.zeros(0, np.int64)
    box = np.stack([points.min(0) - radius, points.max(0) + radius])
    idx = _in_box(means, box, index)
    d, _ = cKDTree(points).query(means[idx], distance_upper_bound=radius, workers=query_workers(len(idx)))
    return idx[np.isfinite(d) & (d <= radius)]


def near_surface(means: np.ndarray, caster: Raycaster, radius: float, index: BoxIndex | None = None) -> np.ndarray:
    """Indices of ``means`` within ``radius`` of the caster's triangle surface or inside it
    (R_asset; ``Raycaster.within``); index: ``BoxIndex(means)``."""
    box = np.stack([caster.vertices.min(0) - radius, caster.vertices.max(0) + radius])
    idx = _in_box(means, box, index)
    if len(idx) == 0:
        return np.zeros(0, np.int64)
    return idx[caster.within(means[idx], radius)]


def reaching_into(data: GaussianSplatData, candidates: np.ndarray, caster: Raycaster, sigmas: float,
                  depth: float) -> np.ndarray:
    """Indices among ``candidates`` (K,) whose longest axis, ``sigmas`` σ either side of the centre,
    ends more than ``depth`` inside the caster's closed mesh (R_reach; ``RemovalConfig.reach_sigmas``)."""
    from phirie_jax.rotations import quat_to_matrix

    if len(candidates) == 0:
        return np.zeros(0, np.int64)
    scales = np.exp(data.log_scales[candidates].astype(np.float64))
    longest = np.argmax(scales, axis=1)
    quats = data.quats[candidates].astype(np.float64)
    norms = np.linalg.norm(quats, axis=1, keepdims=True)
    rot = quat_to_matrix(quats / np.maximum(norms, 1e-12))
    axis = rot[np.arange(len(candidates)), :, longest] * (sigmas * scales[np.arange(len(candidates)), longest])[:, None]
    centres = data.means[candidates].astype(np.float64)
    ends = caster.deep_inside(np.concatenate([centres + axis, centres - axis]), depth).reshape(2, -1)
    return candidates[ends.any(axis=0)]


def enclosed_by(means: np.ndarray, candidates: np.ndarray, caster: Raycaster, up: np.ndarray, directions: int,
                lift: float) -> np.ndarray:
    """Indices among ``candidates`` (K,) walled in by the caster's closed mesh: in every one of
    ``directions`` evenly spread horizontal directions (⊥ ``up``), a ray from the centre, or from
    the centre raised by ``lift`` / 2 or ``lift``, meets the mesh (R_enclosed: the inside of an open
    container, neither near its outer surface nor inside its volume; the raised rays reach the
    walls over a floor at the support's height, below a rounded foot)."""
    from phirie_jax.geometry import rotation_to_z

    if len(candidates) == 0:
        return np.zeros(0, np.int64)
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    to_world = rotation_to_z(up).T        # gravity frame → world
    angles = 2 * np.pi * np.arange(directions) / directions
    rays = np.column_stack([np.cos(angles), np.sin(angles), np.zeros(directions)]) @ to_world.T
    walled = np.zeros((len(candidates), directions), bool)
    for height in (0.0, 0.5 * lift, lift):
        origins = np.repeat(means[candidates] + height * up, directions, axis=0)
        hits = caster.cast(origins, np.tile(rays, (len(candidates), 1)))
        walled |= np.isfinite(hits.depth).reshape(len(candidates), directions)
    return candidates[walled.all(axis=1)]


def read_mask(path: Path) -> np.ndarray:
    import cv2

    mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if mask is None:
        raise OSError(f"mask image unreadable: {path}")
    return mask if mask.ndim == 2 else mask[..., 0]


@dataclasses.dataclass
class MaskJob:
    """One (object, view) of the R_mask pass."""

    obj: int       # index into the objects list
    view: int      # camera index
    label: int
    mask_path: Path
    crop: Crop


def _mask_jobs(objects: list[ObjectInput], cameras: tuple[Camera, ...], config: BackgroundConfig) -> list[MaskJob]:
    """The (object, view) pairs of the R_mask pass: each object's ``mask_views`` largest masks, all
    cropped at one size (one compiled program): the largest any view needs."""
    picked = []
    for k, o in enumerate(objects):
        order = np.argsort(-o.pixels, kind="stable")[: config.removal.mask_views]
        picked += [(k, int(j)) for j in order if int(o.views[j]) < len(cameras) and o.pixels[j] > 0]
    sizes, margin = config.crops.mask_sizes, config.crops.margin_px
    size = max([make_crop(cameras[objects[k].views[j]], 0, objects[k].bboxes[j], sizes, margin).size
                for k, j in picked], default=min(sizes))
    return [MaskJob(k, int(objects[k].views[j]), int(objects[k].labels[j]), objects[k].mask_paths[j],
                    make_crop(cameras[objects[k].views[j]], int(objects[k].views[j]), objects[k].bboxes[j], (size,),
                              margin)) for k, j in picked]


def _job_mask(job: MaskJob, cameras: tuple[Camera, ...], masks: dict[Path, np.ndarray | str]) -> np.ndarray | str:
    """The job's mask image (each file read once: ``masks`` caches it), or the problem (a message)
    that keeps this view from voting."""
    if job.mask_path not in masks:
        try:
            masks[job.mask_path] = read_mask(job.mask_path)
        except OSError as err:
            masks[job.mask_path] = str(err)
    mask = masks[job.mask_path]
    if isinstance(mask, str):
        return mask
    cam = cameras[job.view]
    if mask.shape != (cam.height, cam.width):
        return f"{job.mask_path}: {mask.shape[1]}×{mask.shape[0]}, camera is {cam.width}×{cam.height}"
    return mask


def _job_votes(means: np.ndarray, idx: np.ndarray, job: MaskJob, mask: np.ndarray, image: CropImage,
               cameras: tuple[Camera, ...], config: BackgroundConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One view's votes for the candidates ``idx`` (K,) of one object, from its mask and the crop
    render of those candidates: (K,) bool in the mask and visible, (K,) bool in the mask, (K,) bool
    visible outside the mask (the view saw it as something else).
    means: (N, 3) float64, every Gaussian's centre."""
    cam = cameras[job.view]
    depth = image.depth_normalized
    alpha = image.alpha
    uv, z = job.crop.camera.project(means[idx])
    col = np.floor(uv[:, 0]).astype(np.int64)
    row = np.floor(uv[:, 1]).astype(np.int64)
    size = job.crop.size
    ok = (z > 0) & (col >= 0) & (col < size) & (row >= 0) & (row < size)
    ok[ok] &= job.crop.inside[row[ok], col[ok]]
    full = np.floor(job.crop.to_full(uv[ok])).astype(np.int64)
    fc = np.clip(full[:, 0], 0, cam.width - 1)
    fr = np.clip(full[:, 1], 0, cam.height - 1)
    in_mask = np.zeros(len(idx), bool)
    in_mask[ok] = mask[fr, fc] == job.label
    visible = np.zeros(len(idx), bool)
    r, c = row[ok], col[ok]
    visible[ok] = (alpha[r, c] < DEPTH_ALPHA) | (z[ok] <= depth[r, c] + config.removal.occlusion_tolerance)
    outside = np.zeros(len(idx), bool)
    outside[ok] = ~in_mask[ok]
    return in_mask & visible, in_mask, outside & visible


def _job_images(data: GaussianSplatData, candidates: list[np.ndarray], jobs: list[MaskJob], crops: CropRenderer,
                pad: int) -> list[CropImage | str]:
    """The depth renders of the jobs (each object's candidates in its crop, without colour:
    ``colourless``), in batches (``CropRenderer.render_many``); a batch the renderer refuses is rendered job by job, and a job
    it still refuses gets the problem (a message): that view does not vote."""
    images: list[CropImage | str] = []
    data = colourless(data)  # the votes read depth and alpha only
    per = batch_size(pad, len(jobs))
    for start in range(0, len(jobs), per):
        chunk = jobs[start:start + per]
        try:
            images += crops.render_many([CropJob(data, j.crop, candidates[j.obj]) for j in chunk], pad)
            continue
        except RuntimeError:  # the renderer's buffers: the views of this batch are tried alone
            pass
        for job in chunk:
            try:
                images.append(crops.render(data.subset(candidates[job.obj]), job.crop, pad))
            except RuntimeError as err:
                images.append(f"view {job.view}: {err}")
    return images


def mask_votes(data: GaussianSplatData, objects: list[ObjectInput], cameras: tuple[Camera, ...],
               config: BackgroundConfig, crops: CropRenderer, candidates: list[np.ndarray] | None = None
               ) -> tuple[list[np.ndarray], list[dict], list[np.ndarray]]:
    """R_mask of every object (indices into ``data``), a record per object, and per object the
    candidates ``mask_votes`` views saw, unoccluded, outside its mask (not in R_mask). The (object,
    view) renders of all objects are one pass of batched launches; each mask file is read once.
    candidates: per object, the indices of the Gaussians inside its expanded bounds (computed
    here when not given)."""
    means = data.means.astype(np.float64)
    if candidates is None:
        candidates = [_in_box(means, o.bounds(config.removal.bounds_margin)) for o in objects]
    jobs = _mask_jobs(objects, cameras, config)
    pad = pass_bucket([len(c) for c in candidates])
    votes = [np.zeros(len(c), np.int64) for c in candidates]
    seen = [np.zeros(len(c), np.int64) for c in candidates]
    elsewhere = [np.zeros(len(c), np.int64) for c in candidates]
    used: list[list[int]] = [[] for _ in objects]
    problems: list[list[str]] = [[] for _ in objects]
    masks: dict[Path, np.ndarray | str] = {}
    ready: list[tuple[MaskJob, np.ndarray]] = []
    for job in jobs:
        if len(candidates[job.obj]) == 0:
            continue
        mask = _job_mask(job, cameras, masks)
        if isinstance(mask, str):
            problems[job.obj].append(mask)
        else:
            ready.append((job, mask))
    images = _job_images(data, candidates, [j for j, _ in ready], crops, pad)
    for (job, mask), image in zip(ready, images):
        if isinstance(image, str):
            problems[job.obj].append(image)
            continue
        in_view, in_mask, outside = _job_votes(means, candidates[job.obj], job, mask, image, cameras, config)
        votes[job.obj] += in_view
        seen[job.obj] += in_mask
        elsewhere[job.obj] += outside
        used[job.obj].append(job.view)
    sets, records, seen_elsewhere = [], [], []
    for k, o in enumerate(objects):
        chosen = votes[k] >= config.removal.mask_votes
        sets.append(candidates[k][chosen])
        seen_elsewhere.append(candidates[k][(elsewhere[k] >= config.removal.mask_votes) & ~chosen])
        occluded = (seen[k] >= config.removal.mask_votes) & ~chosen
        records.append({"views": used[k], "candidates": len(candidates[k]),
                        "occluded_rejected": int(occluded.sum()), "problems": problems[k]})
    return sets, records, seen_elsewhere


def support_outside_contact(means: np.ndarray, candidates: np.ndarray, object_points: np.ndarray, up: np.ndarray,
                            base: float, band: float, reach: float) -> np.ndarray:
    """The ``candidates`` (indices into ``means``) that are the support's own surface away from the
    object: at most ``band`` above its ``base`` height (or below it), outside the convex hull, across
    up, of the object's points (``object_points`` (P, 3)) within 2 × ``band`` of the base — the
    object's contact — and farther than ``reach`` from every one of them."""
    from scipy.spatial import Delaunay, QhullError, cKDTree

    up = np.asarray(up, np.float64)
    low = candidates[means[candidates] @ up - base <= band]
    contact = object_points[object_points @ up - base <= 2 * band]
    if len(low) == 0 or len(contact) == 0:
        return low
    across = np.stack(tangent_basis(up), axis=1)  # (3, 2)
    flat = means[low] @ across
    d, _ = cKDTree(contact @ across).query(flat, distance_upper_bound=reach)
    away = ~np.isfinite(d)
    try:
        away &= Delaunay(contact @ across).find_simplex(flat) < 0
    except QhullError:  # a contact of fewer than three points, or on a line: its points alone
        pass
    return low[away]


def _near(caster: Raycaster | None, means: np.ndarray, radius: float) -> Callable[[np.ndarray], np.ndarray]:
    """indices (K,) into ``means`` → (K,) bool: within ``radius`` of the caster's surface (or inside);
    all False without one."""
    if caster is None:
        return lambda idx: np.zeros(len(idx), bool)
    return lambda idx: caster.within(means[idx], radius)


def spared_sets(means: np.ndarray, union: np.ndarray, seen_elsewhere: np.ndarray | None, own: np.ndarray,
                contact: tuple[float, np.ndarray] | None, up, config: BackgroundConfig,
                near_asset: Callable[[np.ndarray], np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """What R_obs ∪ R_asset ∪ R_mask (``union``, indices into ``means`` (N, 3)) gives back: (the
    Gaussians mask views saw unoccluded outside the mask, ``seen_elsewhere``, None: none; the
    support's surface away from the contact, ``support_outside_contact``). ``own``: what the object
    carries, never given back; ``contact``: (its support's height along up, the points (P, 3) that
    are evidence of where it meets it), None: no support sparing. At the contact itself (within
    ``support_band`` of the support and ``contact_reach`` of the contact and of the placed asset,
    ``near_asset``: indices (K,) → (K,) bool, within that reach of it; None: not limited) nothing is given back: a
    Gaussian there straddles the masks' edge, and being seen outside them is no evidence it is not
    the object's (left, it is a ghost where the object stood). A soft support's own surface around
    the contact, farther from the asset, is still given back."""
    up = np.asarray(up, np.float64)
    spared, at_contact = np.zeros(0, np.int64), np.zeros(0, np.int64)
    if contact is not None and config.removal.contact_reach > 0:
        base, points = contact
        low = union[means[union] @ up - base <= config.removal.support_band]
        away = support_outside_contact(means, union, points, up, base, config.removal.support_band,
                                       config.removal.contact_reach)
        at_contact = np.setdiff1d(low, away, assume_unique=True)
        if near_asset is not None and len(at_contact):
            at_contact = at_contact[near_asset(at_contact)]
        spared = np.setdiff1d(away, own)
    r_seen = np.zeros(0, np.int64)
    if seen_elsewhere is not None:
        r_seen = np.setdiff1d(np.setdiff1d(np.intersect1d(seen_elsewhere, union), own), at_contact)
    return r_seen, np.setdiff1d(spared, r_seen, assume_unique=True)


def removal_sets(data: GaussianSplatData, objects: list[ObjectInput], cameras: tuple[Camera, ...],
                 config: BackgroundConfig, crops: CropRenderer, up=(0.0, 0.0, 1.0),
                 contacts: list[tuple[float, np.ndarray]] | None = None) -> tuple[list[np.ndarray], list[dict]]:
    """R_i for every object (sorted unique indices into ``data``) and per-object records with the
    counts of R_obs, R_asset, R_mask and their union. The mask votes of all objects are one
    pass of batched renders (``mask_votes``); each object's mesh is prepared for ray casting once,
    for R_asset, R_enclosed and R_reach. With ``contacts`` (per object its support's height along
    up and the points (P, 3) that are evidence of where it meets it), R_obs ∪ R_asset ∪ R_mask
    spares the support's surface away from the object's contact (``support_outside_contact``,
    ``RemovalConfig.support_band`` and ``contact_reach``)."""
    means = data.means.astype(np.float64)
    index = BoxIndex(means)  # every object's boxes read only their x-slab of the capture
    boxes = [_in_box(means, o.bounds(config.removal.bounds_margin), index) for o in objects]
    masks, mask_records, seen_elsewhere = mask_votes(data, objects, cameras, config, crops, boxes)
    sets, records = [], []
    for k, (o, box, r_mask, mask_record) in enumerate(zip(objects, boxes, masks, mask_records)):
        r_obs = near_points(means, o.q, config.removal.obs_radius, index)
        caster = Raycaster(*o.mesh) if o.mesh is not None and len(o.mesh[1]) else None
        r_asset = (near_surface(means, caster, config.removal.asset_radius, index) if caster
                   else np.zeros(0, np.int64))
        union = np.union1d(np.union1d(r_obs, r_asset), r_mask)
        own = near_points(means, o.visual_means, OWN_GAUSSIAN, index)  # what the object carries is never spared
        near_asset = _near(caster, means, config.removal.contact_reach)
        r_seen, spared = spared_sets(means, union, seen_elsewhere[k] if config.removal.spare_seen_elsewhere else None,
                                     own, None if contacts is None else contacts[k], up, config, near_asset)
        union = np.setdiff1d(union, np.union1d(r_seen, spared), assume_unique=True)
        r_reach, r_enclosed = np.zeros(0, np.int64), np.zeros(0, np.int64)
        if caster is not None:
            rest = np.setdiff1d(box, union, assume_unique=True)
            if config.removal.enclosed_directions > 0:
                r_enclosed = enclosed_by(means, rest, caster, np.asarray(up, np.float64),
                                         config.removal.enclosed_directions, config.removal.enclosed_lift)
                rest = np.setdiff1d(rest, r_enclosed, assume_unique=True)
            if config.removal.reach_sigmas > 0:
                r_reach = reaching_into(data, rest, caster, config.removal.reach_sigmas, config.removal.reach_depth)
            union = np.union1d(union, np.union1d(r_enclosed, r_reach))
        sets.append(union)
        records.append({"obs": len(r_obs), "asset": len(r_asset), "mask": len(r_mask), "enclosed": len(r_enclosed),
                        "reach": len(r_reach), "spared_support": len(spared), "spared_seen": len(r_seen),
                        "union": len(union), "asset_surface": o.mesh is not None, "mask_pass": mask_record})
    return sets, records
