"""nerfstudio / instant-ngp / Blender / ScanNet++ ``transforms.json`` cameras.

Each frame's ``transform_matrix`` is camera-to-world in OpenGL camera axes (x right,
y up, z backwards); ``Camera`` wants world-to-camera in OpenCV axes (x right, y down,
z forward), so the camera's y and z axes are negated and the pose inverted. Pixel
centres are at +0.5 in both (a centred principal point is cx = w / 2), so K is kept.

Intrinsics (``fl_x fl_y cx cy w h``, or ``camera_angle_x``/``camera_angle_y``, and
``k1 k2 k3 k4 p1 p2``) may sit at the top level, in each frame, or both (the frame
wins). Names: when every ``file_path`` starts with the same folder (nerfstudio's
``images/``, Blender's ``./train/``), that folder is the image folder and
``Camera.name`` is relative to it; otherwise names are the paths as written (an
absolute ``file_path`` is named by its file name).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path, PurePosixPath

import numpy as np

from phirie_jax.errors import SceneInputError
from phirie_jax.io.atomic import write_files
from phirie_jax.io.camera import RIGID_TOLERANCE, check_inside, intrinsics_matrix, rigid, sort_by_name
from phirie_jax.io.images import image_size
from phirie_jax.io.jsonfile import read_json_object
from phirie_jax.types import Camera

SUPPORTED_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # flips camera y and z (either way)
_IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")  # tried when file_path names no existing file
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


def read_transforms_json(
    path: str | Path, image_root: str | Path | None = None, *, skip_bad: bool = False,
    scene_root: str | Path | None = None,
) -> list[Camera]:
    """Cameras of every frame (and every ``test_frames`` entry), sorted by name.

    ``file_path`` is relative to the json's folder, or to ``image_root`` when given (as
    ScanNet++'s bare file names need). Frames flagged ``is_bad`` are dropped only when
    ``skip_bad``. ``Camera.image_path`` is the absolute image path (with the extension
    found on disk for Blender's extension-less paths). A path outside that folder (``..`` or
    absolute), or a symbolic link to a file outside ``scene_root`` (default: that folder), is
    refused unless ``camera.outside_paths_allowed``.
    """
    path = Path(path)
    meta = read_json_object(path, "a JSON object with a 'frames' list")
    entries = []
    for key in ("frames", "test_frames"):
        frames = meta.get(key, [] if key == "test_frames" else None)
        if not isinstance(frames, list):
            raise SceneInputError(path, key, "missing or not a list (expected a list of frame objects)")
        for i, frame in enumerate(frames):
            if not isinstance(frame, dict):
                raise SceneInputError(path, f"{key}[{i}]", "expected an object")
            if not (skip_bad and frame.get("is_bad") is True):
                entries.append((f"{key}[{i}]", frame))

    base = Path(os.path.abspath(image_root if image_root is not None else path.parent))
    parts = [_path_parts(path, where, frame) for where, frame in entries]
    relative = [p for p in parts if p[0] != "/"]
    strip = bool(relative) and all(len(p) > 1 and p[0] == relative[0][0] != ".." for p in relative)

    cameras = []
    for (where, frame), p in zip(entries, parts):
        image_path = Path(os.path.abspath(Path(*p) if p[0] == "/" else base.joinpath(*p)))
        check_inside(image_path, base, path, f"{where}: file_path", frame["file_path"], scene_root)
        name = p[-1] if p[0] == "/" else "/".join(p[1:] if strip else p)
        if not image_path.is_file():
            for ext in _IMAGE_EXTENSIONS:
                if image_path.with_name(image_path.name + ext).is_file():
                    image_path, name = image_path.with_name(image_path.name + ext), name + ext
                    check_inside(image_path, base, path, f"{where}: file_path", frame["file_path"], scene_root)
                    break
        K, width, height, model, distortion = _intrinsics(path, where, frame, meta, image_path)
        cameras.append(Camera(
            name=name,
            K=K,
            world_to_camera=_world_to_camera(path, where, frame.get("transform_matrix")),
            width=width,
            height=height,
            model=model,
            distortion=distortion,
            image_path=image_path,
        ))
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        problem = f"{dup!r} appears in more than one frame (expected unique images)"
        raise SceneInputError(path, "file_path", problem)
    return sort_by_name(cameras)


def write_transforms_json(path: str | Path, cameras: list[Camera], image_dir_name: str = "images") -> None:
    """Write nerfstudio's ``transforms.json`` (OpenGL camera-to-world) for ``cameras``.

    ``file_path`` is ``image_dir_name/name``. Intrinsics go at the top level when every
    camera has the same, else into each frame; ``camera_model`` is PINHOLE (or
    SIMPLE_PINHOLE when the camera says so) without distortion, OPENCV with it.
    Written to a temporary name beside ``path`` and renamed.
    """
    path = Path(path)
    if not image_dir_name or any(c in image_dir_name for c in "/\\") or image_dir_name in (".", ".."):
        raise ValueError(f"image_dir_name {image_dir_name!r}: expected one folder name")
    cameras = sort_by_name(list(cameras))
    fields = [_intrinsic_fields(c) for c in cameras]
    shared = all(f == fields[0] for f in fields)
    meta: dict = dict(fields[0]) if shared and fields else {}
    frames = []
    for camera, own in zip(cameras, fields):
        if not camera.name or camera.name.startswith("/") or "\\" in camera.name:
            raise ValueError(f"camera name {camera.name!r}: expected a relative path with '/' separators")
        frame = {"file_path": f"{image_dir_name}/{camera.name}",
                 "transform_matrix": _opengl_camera_to_world(camera).tolist()}
        if not shared:
            frame.update(own)
        frames.append(frame)
    meta["frames"] = frames
    write_files(path.parent, {path.name: (json.dumps(meta, indent=2) + "\n").encode("utf-8")})


# --- reading -----------------------------------------------------------------------------


def _path_parts(path: Path, where: str, frame: dict) -> tuple[str, ...]:
    value = frame.get("file_path")
    if not isinstance(value, str) or not value.strip():
        raise SceneInputError(path, f"{where}: file_path", "missing (expected the image path as a string)")
    parts = PurePosixPath(value.strip().replace("\\", "/")).parts  # drops "./" components
    if not parts or parts == ("/",):
        raise SceneInputError(path, f"{where}: file_path", f"{value!r} names no file")
    return parts


def _number(value, path: Path, field: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise SceneInputError(path, field, f"{value!r} (expected a finite number)")
    return float(value)


@dataclasses.dataclass(frozen=True)
class _Fields:
    """One frame's camera fields: its own value of a key wins over the top level's."""

    path: Path
    where: str
    frame: dict
    meta: dict

    def get(self, key: str):
        """(value or None, field name for messages)."""
        if key in self.frame:
            return self.frame[key], f"{self.where}: {key}"
        return self.meta.get(key), key

    def number(self, key: str, default: float) -> float:
        value, field = self.get(key)
        return default if value is None else _number(value, self.path, field)


def _intrinsics(path: Path, where: str, frame: dict, meta: dict, image_path: Path):
    """(K (3, 3), width, height, model, distortion (D,)) of one frame."""
    fields = _Fields(path, where, frame, meta)
    width, height = _image_size(fields, image_path)
    fx, fx_field = _focal(fields, "x", width)
    if fx is None:
        raise SceneInputError(
            path, f"{where}: fl_x", "missing (expected fl_x or camera_angle_x, here or at the top level)"
        )
    fy, fy_field = _focal(fields, "y", height)
    if fy is None:  # square pixels unless told otherwise
        fy, fy_field = fx, fx_field
    for value, field in ((fx, fx_field), (fy, fy_field)):
        if value <= 0:
            raise SceneInputError(path, field, f"{value} (expected a positive focal length in pixels)")
    cx = fields.number("cx", width / 2)  # instant-ngp / Blender default
    cy = fields.number("cy", height / 2)
    model, distortion = _lens(fields)
    return intrinsics_matrix(fx, fy, cx, cy), width, height, model, distortion


def _image_size(fields: _Fields, image_path: Path) -> tuple[int, int]:
    """(width, height): ``w``/``h``, else read from the image."""
    size = []
    for key in ("w", "h"):
        value, field = fields.get(key)
        if value is None:
            if not image_path.is_file():
                raise SceneInputError(fields.path, field, f"missing (expected w and h, or the image {image_path} "
                                      "to read the size from)")
            value = image_size(image_path)[len(size)]
        number = _number(value, fields.path, field)
        if number <= 0 or number != int(number):
            raise SceneInputError(fields.path, field, f"{value!r} (expected a positive whole number of pixels)")
        size.append(int(number))
    return size[0], size[1]


def _focal(fields: _Fields, axis: str, pixels: int) -> tuple[float | None, str | None]:
    """(focal length in pixels along ``axis`` from ``fl_<axis>`` or ``camera_angle_<axis>``, the field
    it came from as messages name it: ``frames[3]: fl_x`` or the top level's ``fl_x``); (None, None)
    if neither."""
    for source in (fields.frame, fields.meta):  # a frame's own value, in either form, beats the top level
        if f"fl_{axis}" in source:
            field = fields.get(f"fl_{axis}")[1] if source is fields.frame else f"fl_{axis}"
            return _number(source[f"fl_{axis}"], fields.path, field), field
        if f"camera_angle_{axis}" in source:
            field = fields.get(f"camera_angle_{axis}")[1] if source is fields.frame else f"camera_angle_{axis}"
            angle = _number(source[f"camera_angle_{axis}"], fields.path, field)
            if not 0 < angle < math.pi:
                raise SceneInputError(fields.path, field, f"{angle} (expected a field of view in radians, 0..pi)")
            return 0.5 * pixels / math.tan(0.5 * angle), field
    return None, None


def _lens(fields: _Fields) -> tuple[str, np.ndarray]:
    """(camera model, OpenCV distortion (D,)) from ``camera_model``, ``is_fisheye`` and k1..p2."""
    path = fields.path
    coeffs = {key: fields.number(key, 0.0) for key in _DISTORTION_KEYS}
    model, field = fields.get("camera_model")
    fisheye, _ = fields.get("is_fisheye")
    if fisheye is True or (model is not None and model not in SUPPORTED_MODELS):
        raise SceneInputError(
            path, field, f"unsupported camera model {model if model is not None else 'fisheye'} "
            f"(supported: {', '.join(SUPPORTED_MODELS)} or unset; undistort the images first)",
        )
    distorted = any(coeffs[k] != 0.0 for k in _DISTORTION_KEYS)
    if model in ("PINHOLE", "SIMPLE_PINHOLE") and distorted:
        raise SceneInputError(path, field, f"{model} with nonzero distortion {coeffs} (expected OPENCV)")
    if model is None:
        model = "OPENCV" if distorted else "PINHOLE"
    distortion = []
    if model == "OPENCV":
        if coeffs["k4"] != 0.0:
            raise SceneInputError(path, fields.get("k4")[1], f"{coeffs['k4']} (OPENCV has no k4; expected 0)")
        distortion = [coeffs[k] for k in ("k1", "k2", "p1", "p2")] + ([coeffs["k3"]] if coeffs["k3"] else [])
    return model, np.asarray(distortion, dtype=np.float64)


def _world_to_camera(path: Path, where: str, matrix) -> np.ndarray:
    """(4, 4) OpenCV world-to-camera from an OpenGL camera-to-world ``transform_matrix``."""
    field = f"{where}: transform_matrix"
    if matrix is None:
        raise SceneInputError(path, field, "missing (expected a 4x4 camera-to-world matrix)")
    try:
        matrix = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise SceneInputError(path, field, "expected a 4x4 matrix of numbers") from None
    c2w = rigid(matrix, path, field) @ _GL_TO_CV
    out = np.eye(4)
    out[:3, :3] = c2w[:3, :3].T
    out[:3, 3] = -c2w[:3, :3].T @ c2w[:3, 3]
    return out


# --- writing -----------------------------------------------------------------------------


def _opengl_camera_to_world(camera: Camera) -> np.ndarray:
    """(4, 4) OpenGL camera-to-world of a rigid OpenCV world-to-camera."""
    m = np.asarray(camera.world_to_camera, dtype=np.float64)
    rot = m[:3, :3]
    if (m.shape != (4, 4) or not np.all(np.isfinite(m)) or np.any(m[3] != (0.0, 0.0, 0.0, 1.0))
            or np.abs(rot.T @ rot - np.eye(3)).max() > RIGID_TOLERANCE or np.linalg.det(rot) <= 0):
        raise ValueError(f"camera {camera.name!r}: world_to_camera is not a rigid 4x4 transform")
    return camera.camera_to_world @ _GL_TO_CV


def _intrinsic_fields(camera: Camera) -> dict:
    K = np.asarray(camera.K, dtype=np.float64)
    if K.shape != (3, 3) or K[0, 1] != 0 or K[1, 0] != 0 or np.any(K[2] != (0.0, 0.0, 1.0)):
        raise ValueError(f"camera {camera.name!r}: K must be a pinhole matrix without skew, got {K.tolist()}")
    d = np.asarray(camera.distortion, dtype=np.float64).ravel()
    if np.any(d[5:] != 0):
        raise ValueError(f"camera {camera.name!r}: distortion {d.tolist()} has terms beyond k1 k2 p1 p2 k3")
    distorted = bool(np.any(d != 0))
    fx, fy = float(K[0, 0]), float(K[1, 1])
    if camera.model == "OPENCV" or distorted:
        model = "OPENCV"
    elif camera.model == "SIMPLE_PINHOLE" and fx == fy:
        model = "SIMPLE_PINHOLE"
    else:
        model = "PINHOLE"
    fields = {"camera_model": model, "fl_x": fx, "fl_y": fy, "cx": float(K[0, 2]), "cy": float(K[1, 2]),
              "w": int(camera.width), "h": int(camera.height)}
    if model == "OPENCV":
        k = np.pad(d[:5], (0, 5 - min(d.size, 5)))
        fields.update(k1=float(k[0]), k2=float(k[1]), p1=float(k[2]), p2=float(k[3]))
        if k[4] != 0:
            fields["k3"] = float(k[4])
    return fields
