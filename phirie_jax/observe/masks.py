"""Per-view instance masks, from any source, behind one record: ``ViewMasks``.

Sources:
- ``files``: ``masks/<image stem>.png`` (16-bit, 0 = none, k = instance k). The value is
  the instance's identity in every view (docs/architecture.md "Contracts"). ScanNet++ annotations
  (``scans/segments_anno.json`` + ``scans/segments.json`` over the scan mesh's vertices)
  become masks of the same kind by projecting the labelled mesh (``vertex_label_image``).
- external segmenters (SAM-family outputs brought by the user), a folder with per image
  ``<image stem>.png`` (8- or 16-bit, 0 = none, k = segment k *of that image*) and an
  optional ``<image stem>.json``::

      {"segments": [{"label": 1, "score": 0.93, "category": "mug"}, ...]}

  Labels carry no identity across images; association decides which segments are one
  object. A segment the JSON lists but the PNG lacks is recorded, not fatal.
- ``auto``: ``phirie_jax.observe.auto`` (supports, clusters, projection with occlusion).

Problems with one view (unreadable or wrongly sized mask, no camera for a mask file,
a camera without a usable pose) are returned as ``ViewFailure`` records and the other
views go on.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from phirie_jax.errors import SceneInputError
from phirie_jax.types import Camera, SceneInput


@dataclasses.dataclass(frozen=True)
class Segment:
    label: int                  # its value in the view's label image
    instance_id: int | None     # identity across views when the source has one
    category: str | None = None
    score: float | None = None


@dataclasses.dataclass(frozen=True)
class ViewMasks:
    view: int                       # camera index
    labels: np.ndarray              # (H, W) int64, 0 = none
    segments: dict[int, Segment]    # label → segment (every non-zero label present, plus listed ones)
    path: str | None = None         # where the masks came from


@dataclasses.dataclass(frozen=True)
class ViewFailure:
    view: int | None
    path: str | None
    reason: str

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def camera_problem(camera: Camera) -> str | None:
    """Why a camera cannot be used for lifting, or None."""
    if camera.world_to_camera is None or np.shape(camera.world_to_camera) != (4, 4):
        return "camera has no pose (expected a 4x4 world-to-camera matrix)"
    if not np.all(np.isfinite(camera.world_to_camera)) or not np.all(np.isfinite(camera.K)):
        return "camera pose or intrinsics are not finite"
    if camera.K[0, 0] <= 0 or camera.K[1, 1] <= 0:
        return f"focal length {camera.K[0, 0]}, {camera.K[1, 1]} (expected > 0)"
    return None


def read_label_png(path: Path, camera: Camera) -> np.ndarray:
    """(H, W) int64 labels of an 8/16-bit single-channel PNG sized like ``camera``.

    Raises ``SceneInputError`` naming the file and what was expected.
    """
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise SceneInputError(path, None, "not a readable image (expected a 16-bit PNG of instance ids)")
    if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
        raise SceneInputError(path, "pixel format", f"{image.dtype} with shape {image.shape} "
                              "(expected one 8- or 16-bit channel of instance ids)")
    if image.shape != (camera.height, camera.width):
        raise SceneInputError(path, "mask size", f"{image.shape[1]}×{image.shape[0]} "
                              f"(expected {camera.width}×{camera.height} like camera '{camera.name}')")
    return image.astype(np.int64)


def _segments_of(labels: np.ndarray, identity: bool) -> dict[int, Segment]:
    present = np.unique(labels)
    return {int(k): Segment(int(k), int(k) if identity else None) for k in present if k != 0}


def file_masks(cameras: tuple[Camera, ...], paths: tuple[Path | None, ...]) -> Iterator[ViewMasks | ViewFailure]:
    """Mask files aligned with the cameras (``SceneInput.masks``); values are instance ids."""
    for view, (camera, path) in enumerate(zip(cameras, paths)):
        if path is None:
            continue  # a view without a mask file simply shows nothing
        problem = camera_problem(camera)
        if problem:
            yield ViewFailure(view, str(path), problem)
            continue
        try:
            labels = read_label_png(Path(path), camera)
        except SceneInputError as err:
            yield ViewFailure(view, str(path), str(err))
            continue
        yield ViewMasks(view, labels, _segments_of(labels, identity=True), str(path))


def check_mask_source(scene: SceneInput, masks: str | Path | None) -> None:
    """Refuse a ``--masks`` source the scene cannot give, with the error observation would raise,
    but before anything is written. None (the default) and "auto" always can."""
    if masks is None or masks == "auto":
        return
    if masks == "files":
        if scene.masks is None and (scene.segments_anno is None or scene.surface_mesh is None):
            raise SceneInputError(scene.root / "masks", "--masks files",
                                  "no masks/ folder and no ScanNet++ annotations (use --masks auto or a folder)")
        return
    _mask_pngs(Path(masks))


def file_mask_ids(scene: SceneInput, masks: str | Path | None) -> set[int] | None:
    """The instance ids the scene's mask files hold when observation reads them (``masks`` is
    "files", or None with a ``masks/`` folder); None when observation gives the ids (automatic
    masks, an external segmenter's per-image labels, ScanNet++ annotations)."""
    import cv2

    if masks not in (None, "files") or scene.masks is None:
        return None
    ids: set[int] = set()
    for path in scene.masks:
        image = None if path is None else cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is not None:
            ids.update(int(k) for k in np.unique(image) if k != 0)
    return ids


def _mask_pngs(folder: Path) -> list[Path]:
    """The label images of an external segmenter's folder; ``SceneInputError`` if there are none."""
    if not folder.is_dir():
        raise SceneInputError(folder, "--masks", "folder not found (expected 'files', 'auto' or a folder "
                              "of <image stem>.png label images with optional .json scores)")
    pngs = sorted(folder.glob("*.png"))
    if not pngs:
        raise SceneInputError(folder, "--masks", "no .png label images in the folder")
    return pngs


def external_masks(folder: Path, cameras: tuple[Camera, ...]) -> Iterator[ViewMasks | ViewFailure]:
    """An external segmenter's per-image PNG (+ JSON) folder; see the module docstring."""
    folder = Path(folder)
    pngs = _mask_pngs(folder)
    by_stem = {Path(c.name).stem: i for i, c in enumerate(cameras)}
    for path in pngs:
        view = by_stem.get(path.stem)
        if view is None:
            yield ViewFailure(None, str(path), f"no camera for image stem '{path.stem}'")
            continue
        problem = camera_problem(cameras[view])
        if problem:
            yield ViewFailure(view, str(path), problem)
            continue
        try:
            labels = read_label_png(path, cameras[view])
            listed = _read_segment_json(path.with_suffix(".json"))
        except SceneInputError as err:
            yield ViewFailure(view, str(path), str(err))
            continue
        segments = _segments_of(labels, identity=False)
        for label, meta in listed.items():
            segments[label] = Segment(label, None, meta.get("category"), meta.get("score"))
        yield ViewMasks(view, labels, segments, str(path))


def _read_segment_json(path: Path) -> dict[int, dict]:
    if not path.exists():
        return {}
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise SceneInputError(path, None, f"not valid JSON ({e})") from None
    items = data.get("segments") if isinstance(data, dict) else None
    if not isinstance(items, list):
        raise SceneInputError(path, "segments", "expected a list of {label, score, category}")
    out = {}
    for n, item in enumerate(items):
        label = item.get("label") if isinstance(item, dict) else None
        if isinstance(label, bool) or not isinstance(label, int) or label <= 0:
            raise SceneInputError(path, f"segments[{n}].label", f"{label!r} (expected a positive integer)")
        score = item.get("score")
        if score is not None and (isinstance(score, bool) or not isinstance(score, (int, float))
                                  or not 0 <= score <= 1):
            raise SceneInputError(path, f"segments[{n}].score", f"{score!r} (expected a number in [0, 1])")
        category = item.get("category")
        if category is not None and not isinstance(category, str):
            raise SceneInputError(path, f"segments[{n}].category", f"{category!r} (expected a string)")
        out[label] = {"score": None if score is None else float(score), "category": category}
    return out


def vertex_label_image(raycaster, vertex_labels: np.ndarray, camera: Camera) -> np.ndarray:
    """(H, W) labels of a mesh seen from a camera with occlusion: the first-hit triangle's
    vertex with the largest barycentric weight gives the pixel its label (0 where missed)."""
    hits, _, _ = raycaster.cast_camera(camera)
    labels = np.zeros(len(hits.depth), np.int64)
    hit = hits.hit
    corner = np.argmax(hits.bary[hit], axis=1)
    labels[hit] = vertex_labels[raycaster.faces[hits.face[hit], corner]]
    return labels.reshape(camera.height, camera.width)


def projected_masks(raycaster, vertex_labels: np.ndarray, cameras: tuple[Camera, ...],
                    categories: dict[int, str] | None = None, source: str = "projected"
                    ) -> Iterator[ViewMasks | ViewFailure]:
    """Per-view masks of a labelled surface (vertex labels = instance ids)."""
    categories = categories or {}
    for view, camera in enumerate(cameras):
        problem = camera_problem(camera)
        if problem:
            yield ViewFailure(view, None, problem)
            continue
        labels = vertex_label_image(raycaster, vertex_labels, camera)
        segments = {k: Segment(k, k, categories.get(k)) for k in map(int, np.unique(labels)) if k}
        yield ViewMasks(view, labels, segments, source)


def scannetpp_vertex_labels(segments_anno: Path, num_vertices: int) -> tuple[np.ndarray, dict[int, str]]:
    """ScanNet++ ``segments_anno.json`` (+ ``segments.json`` beside it) → per-vertex instance
    ids (objectId + 1, 0 = none) and {id: label}."""
    segments_path = Path(segments_anno).with_name("segments.json")
    try:
        anno = json.loads(Path(segments_anno).read_text(encoding="utf-8"))
        seg = json.loads(segments_path.read_text(encoding="utf-8"))
    except FileNotFoundError as e:
        raise SceneInputError(e.filename, None, "file not found (ScanNet++ annotations need "
                              "segments_anno.json and segments.json)") from None
    except json.JSONDecodeError as e:
        raise SceneInputError(segments_anno, None, f"not valid JSON ({e})") from None
    seg_indices = np.asarray(seg.get("segIndices", []), np.int64)
    if len(seg_indices) != num_vertices:
        raise SceneInputError(segments_path, "segIndices", f"{len(seg_indices)} entries "
                              f"(expected one per scan mesh vertex, {num_vertices})")
    labels = np.zeros(num_vertices, np.int64)
    names = {}
    order = np.argsort(seg_indices, kind="stable")
    sorted_idx = seg_indices[order]
    for group in anno.get("segGroups", []):
        instance = int(group["objectId"]) + 1
        names[instance] = str(group.get("label", "")) or None
        segs = np.asarray(group.get("segments", []), np.int64)
        lo, hi = np.searchsorted(sorted_idx, segs), np.searchsorted(sorted_idx, segs, side="right")
        for a, b in zip(lo, hi):
            labels[order[a:b]] = instance
    return labels, names
