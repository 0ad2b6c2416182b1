"""COLMAP sparse models (``cameras``, ``images``, ``points3D``; ``.txt`` or ``.bin``).

COLMAP's ``images`` record holds the world-to-camera rotation as a unit quaternion
(w, x, y, z) and translation, in OpenCV camera axes, with pixel centres at +0.5:
exactly the ``Camera`` convention, so no axis or pixel shift is applied here.

Supported camera models are the pinhole ones and those whose distortion is a subset
of OpenCV's (k1, k2, p1, p2); fisheye and thin-prism models are refused with a hint.
``Camera.distortion`` is kept in OpenCV order: SIMPLE_RADIAL → [k, 0, 0, 0],
RADIAL → [k1, k2, 0, 0], OPENCV → [k1, k2, p1, p2], pinhole models → [].
"""

from __future__ import annotations

import dataclasses
import os
import re
import struct
from pathlib import Path

import numpy as np

from phirie_jax.errors import SceneInputError
from phirie_jax.io.atomic import write_files
from phirie_jax.io.camera import check_inside, intrinsics_matrix, sort_by_name
from phirie_jax.types import Camera

SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
# COLMAP's model ids (src/colmap/sensor/models.h); only the first five are read.
MODEL_NAMES = (
    "SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "OPENCV_FISHEYE",
    "FULL_OPENCV", "FOV", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "THIN_PRISM_FISHEYE",
    "RAD_TAN_THIN_PRISM_FISHEYE",
)
_PARAMS = {  # parameter names of the supported models, in COLMAP order
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
}
STEMS = ("cameras", "images", "points3D")
# Rotations further than this from orthonormal are not rigid poses and are refused on write.
RIGID_TOLERANCE = 1e-5
_GREY = 128


@dataclasses.dataclass(frozen=True)
class SparsePoints:
    """COLMAP's triangulated points."""

    xyz: np.ndarray    # (P, 3) float64 world coordinates
    rgb: np.ndarray    # (P, 3) uint8 colours
    error: np.ndarray  # (P,) float64 mean reprojection error in pixels


@dataclasses.dataclass(frozen=True)
class _Intrinsics:
    camera_id: int
    model: str
    width: int
    height: int
    params: tuple[float, ...]


@dataclasses.dataclass(frozen=True)
class _Image:
    image_id: int
    qvec: np.ndarray  # (4,) unit quaternion w, x, y, z
    tvec: np.ndarray  # (3,)
    camera_id: int
    name: str


# --- public API ------------------------------------------------------------------------


def read_colmap_model(
    sparse_dir: str | Path, image_dir: str | Path | None = None, scene_root: str | Path | None = None
) -> tuple[list[Camera], np.ndarray | None]:
    """Cameras (sorted by image name) and the (P, 3) float64 point positions, or None.

    Each of ``cameras``, ``images`` and ``points3D`` is read from its ``.bin`` file when
    present, else from its ``.txt`` file (COLMAP's preference); ``points3D`` is optional.
    When ``image_dir`` is given, ``Camera.image_path`` is ``image_dir / name`` (absolute); a name
    leading outside ``image_dir``, or a symbolic link to a file outside ``scene_root`` (default:
    ``image_dir``), is refused unless ``camera.outside_paths_allowed``.
    """
    sparse_dir = Path(sparse_dir)
    cameras_path = _find(sparse_dir, "cameras", required=True)
    images_path = _find(sparse_dir, "images", required=True)
    intrinsics = _read_cameras(cameras_path)
    root = None if image_dir is None else Path(os.path.abspath(image_dir))  # symlinks kept

    cameras: list[Camera] = []
    seen: dict[str, int] = {}
    for image in _read_images(images_path):
        where = f"image {image.image_id}"
        if image.camera_id not in intrinsics:
            raise SceneInputError(images_path, where, f"camera_id {image.camera_id} not in {cameras_path.name}")
        if image.name in seen:
            raise SceneInputError(
                images_path, where, f"name {image.name!r} repeats image {seen[image.name]} (expected unique names)"
            )
        seen[image.name] = image.image_id
        if root is not None:
            check_inside(root / image.name, root, images_path, f"{where}: name", image.name, scene_root)
        cam = intrinsics[image.camera_id]
        K, distortion = _intrinsics(cam)
        cameras.append(Camera(
            name=image.name,
            K=K,
            world_to_camera=_world_to_camera(image.qvec, image.tvec),
            width=cam.width,
            height=cam.height,
            model=cam.model,
            distortion=distortion,
            image_path=None if root is None else root / image.name,
        ))
    points = read_colmap_points(sparse_dir)
    return sort_by_name(cameras), None if points is None else points.xyz


def read_colmap_points(sparse_dir: str | Path) -> SparsePoints | None:
    """The model's ``points3D`` (.bin preferred over .txt), or None when neither file exists."""
    path = _find(Path(sparse_dir), "points3D", required=False)
    if path is None:
        return None
    return _read_points_bin(path) if path.suffix == ".bin" else _read_points_txt(path)


def write_colmap_text(
    sparse_dir: str | Path,
    cameras: list[Camera],
    points: np.ndarray | None = None,
    colors: np.ndarray | None = None,
) -> None:
    """Write ``cameras.txt``, ``images.txt`` and ``points3D.txt`` into ``sparse_dir``.

    ``points`` (P, 3); ``colors`` (P, 3) uint8, mid-grey when absent. One COLMAP camera
    per distinct intrinsics; image ids follow name order; points3D.txt is written even
    when empty (COLMAP expects all three). Every file goes to a temporary name in the
    folder first and is renamed once all are written, so none is ever half-written.
    """
    _write(Path(sparse_dir), cameras, points, colors, binary=False)


def write_colmap_binary(
    sparse_dir: str | Path,
    cameras: list[Camera],
    points: np.ndarray | None = None,
    colors: np.ndarray | None = None,
) -> None:
    """Same as ``write_colmap_text`` in COLMAP's binary format (``.bin`` files)."""
    _write(Path(sparse_dir), cameras, points, colors, binary=True)


# --- model ↔ Camera ----------------------------------------------------------------------


def _find(sparse_dir: Path, stem: str, *, required: bool) -> Path | None:
    for ext in (".bin", ".txt"):
        path = sparse_dir / f"{stem}{ext}"
        if path.is_file():
            return path
    if not required:
        return None
    if not sparse_dir.is_dir():
        raise SceneInputError(sparse_dir, None, "COLMAP sparse folder not found")
    raise SceneInputError(sparse_dir, stem, f"missing (expected {stem}.bin or {stem}.txt in the folder)")


def _unsupported(path: Path, camera_id: int, model: str) -> SceneInputError:
    return SceneInputError(
        path, f"camera {camera_id}",
        f"unsupported camera model {model} (supported: {', '.join(SUPPORTED_MODELS)}; "
        "undistort the images with `colmap image_undistorter` first)",
    )


def _checked_intrinsics(path: Path, where: str, camera_id: int, model: str, width: int, height: int,
                        params: list[float]) -> _Intrinsics:
    if model not in _PARAMS:
        raise _unsupported(path, camera_id, model)
    names = _PARAMS[model]
    if len(params) != len(names):
        raise SceneInputError(
            path, where, f"{model} has {len(names)} parameters ({' '.join(names)}), got {len(params)}"
        )
    if width <= 0 or height <= 0:
        raise SceneInputError(path, where, f"image size {width}x{height} (expected positive)")
    if not all(np.isfinite(params)) or min(params[: 2 if model in ("PINHOLE", "OPENCV") else 1]) <= 0:
        raise SceneInputError(path, where, f"parameters {params} (expected finite values, focal > 0)")
    return _Intrinsics(camera_id, model, width, height, tuple(float(p) for p in params))


def _intrinsics(cam: _Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """(3, 3) K and (D,) OpenCV-order distortion of a supported COLMAP camera."""
    p = cam.params
    if cam.model == "SIMPLE_PINHOLE":
        return intrinsics_matrix(p[0], p[0], p[1], p[2]), np.zeros(0)
    if cam.model == "PINHOLE":
        return intrinsics_matrix(p[0], p[1], p[2], p[3]), np.zeros(0)
    if cam.model == "SIMPLE_RADIAL":
        return intrinsics_matrix(p[0], p[0], p[1], p[2]), np.array([p[3], 0.0, 0.0, 0.0])
    if cam.model == "RADIAL":
        return intrinsics_matrix(p[0], p[0], p[1], p[2]), np.array([p[3], p[4], 0.0, 0.0])
    return intrinsics_matrix(p[0], p[1], p[2], p[3]), np.array(p[4:8], dtype=np.float64)


def _model_params(camera: Camera) -> tuple[str, tuple[float, ...]]:
    """The COLMAP model and parameters reproducing ``camera``'s K and distortion exactly.

    The camera's own model is kept when it is supported and reproduces them; otherwise
    PINHOLE (no distortion) or OPENCV.
    """
    K = np.asarray(camera.K, dtype=np.float64)
    if K.shape != (3, 3) or K[0, 1] != 0 or K[1, 0] != 0 or np.any(K[2] != (0.0, 0.0, 1.0)):
        raise ValueError(f"camera {camera.name!r}: K must be a pinhole matrix without skew, got {K.tolist()}")
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    d = np.asarray(camera.distortion, dtype=np.float64).ravel()
    if np.any(d[4:] != 0):
        raise ValueError(
            f"camera {camera.name!r}: distortion {d.tolist()} has terms beyond k1, k2, p1, p2, "
            f"which none of {', '.join(SUPPORTED_MODELS)} holds"
        )
    k1, k2, p1, p2 = (float(v) for v in np.pad(d[:4], (0, 4 - min(d.size, 4))))
    square, plain = fx == fy, k1 == k2 == p1 == p2 == 0.0
    fits = {
        "SIMPLE_PINHOLE": (square and plain, (fx, cx, cy)),
        "PINHOLE": (plain, (fx, fy, cx, cy)),
        "SIMPLE_RADIAL": (square and k2 == p1 == p2 == 0.0, (fx, cx, cy, k1)),
        "RADIAL": (square and p1 == p2 == 0.0, (fx, cx, cy, k1, k2)),
        "OPENCV": (True, (fx, fy, cx, cy, k1, k2, p1, p2)),
    }
    keep = camera.model in fits and fits[camera.model][0]
    model = camera.model if keep else ("PINHOLE" if plain else "OPENCV")
    return model, fits[model][1]


def _world_to_camera(qvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """(4, 4) from COLMAP's unit quaternion (w, x, y, z) and translation (3,)."""
    w, x, y, z = qvec
    out = np.eye(4)
    out[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    out[:3, 3] = tvec
    return out


def _quaternion(m: np.ndarray) -> np.ndarray:
    """(4,) unit quaternion (w, x, y, z), w >= 0, of a (3, 3) rotation.

    Built from the largest of the four squared components, so it stays accurate
    for rotations near 180°.
    """
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    squares = (1 + trace, 1 + m[0, 0] - m[1, 1] - m[2, 2],
               1 - m[0, 0] + m[1, 1] - m[2, 2], 1 - m[0, 0] - m[1, 1] + m[2, 2])
    i = int(np.argmax(squares))
    s = 2.0 * np.sqrt(squares[i])  # = 4 |q_i|
    if i == 0:
        q = [s / 4, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif i == 1:
        q = [(m[2, 1] - m[1, 2]) / s, s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif i == 2:
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s]
    else:
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4]
    q = np.asarray(q, dtype=np.float64)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def _pose(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(qvec (4,), tvec (3,)) of a rigid world-to-camera matrix; ValueError if not rigid."""
    m = np.asarray(camera.world_to_camera, dtype=np.float64)
    rigid = (
        m.shape == (4, 4)
        and np.all(np.isfinite(m))
        and np.all(m[3] == (0.0, 0.0, 0.0, 1.0))
        and np.abs(m[:3, :3].T @ m[:3, :3] - np.eye(3)).max() <= RIGID_TOLERANCE
        and np.linalg.det(m[:3, :3]) > 0
    )
    if not rigid:
        raise ValueError(f"camera {camera.name!r}: world_to_camera is not a rigid 4x4 transform")
    return _quaternion(m[:3, :3]), m[:3, 3].copy()


def _normalized_qvec(q: list[float], path: Path, where: str) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if not np.isfinite(norm) or norm < 1e-6:
        raise SceneInputError(path, where, f"quaternion {q.tolist()} (expected a finite, nonzero QW QX QY QZ)")
    return q / norm


def _check_name(name: str) -> None:
    if not name or name != name.strip() or any(c in name for c in "\n\r\0"):
        raise ValueError(f"image name {name!r} cannot be stored in a COLMAP model "
                         "(expected no line breaks, NUL or surrounding spaces)")


# --- text format -------------------------------------------------------------------------


def _text(path: Path) -> list[str]:
    try:
        return path.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError as e:
        problem = f"not UTF-8 text at byte {e.start} (a binary file named .txt?)"
        raise SceneInputError(path, None, problem) from None


def _data_lines(path: Path):
    """(line number, stripped line) of every line that is neither blank nor a comment."""
    for number, line in enumerate(_text(path), start=1):
        line = line.strip()
        if line and not line.startswith("#"):
            yield number, line


def _numbers(tokens: list[str], kind, path: Path, where: str, what: str) -> list:
    try:
        return [kind(t) for t in tokens]
    except ValueError:
        problem = f"{what}: expected {kind.__name__} values, got {' '.join(tokens)}"
        raise SceneInputError(path, where, problem) from None


def _read_cameras(path: Path) -> dict[int, _Intrinsics]:
    if path.suffix == ".bin":
        return _read_cameras_bin(path)
    out: dict[int, _Intrinsics] = {}
    for number, line in _data_lines(path):
        where = f"line {number}"
        tokens = line.split()
        if len(tokens) < 4:
            raise SceneInputError(path, where, f"expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[], got {line!r}")
        camera_id, width, height = _numbers([tokens[0], tokens[2], tokens[3]], int, path, where,
                                            "CAMERA_ID WIDTH HEIGHT")
        params = _numbers(tokens[4:], float, path, where, "PARAMS")
        if camera_id in out:
            raise SceneInputError(path, where, f"camera {camera_id} defined twice")
        out[camera_id] = _checked_intrinsics(path, where, camera_id, tokens[1], width, height, params)
    return out


# A POINTS2D line holds only numbers; an image line always has a name.
_POINTS2D = re.compile(r"[\s0-9.eE+-]*")


def _image_line(line: str, path: Path, number: int) -> _Image | None:
    tokens = line.split(maxsplit=9)
    if len(tokens) != 10:
        return None
    where = f"line {number}"
    image_id, camera_id = _numbers([tokens[0], tokens[8]], int, path, where, "IMAGE_ID CAMERA_ID")
    values = _numbers(tokens[1:8], float, path, where, "QW QX QY QZ TX TY TZ")
    if not np.all(np.isfinite(values[4:])):
        raise SceneInputError(path, where, f"translation {values[4:]} (expected finite values)")
    qvec = _normalized_qvec(values[:4], path, f"image {image_id}")
    return _Image(image_id, qvec, np.asarray(values[4:7]), camera_id, tokens[9])


def _read_images_txt(path: Path) -> list[_Image]:
    """Image lines, each followed by its POINTS2D line (which may be empty or missing)."""
    lines = _text(path)
    images: list[_Image] = []
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        i += 1
        if not line or line.startswith("#"):
            continue
        image = _image_line(line, path, i)
        if image is None:
            raise SceneInputError(
                path, f"line {i}", f"expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, got {line[:80]!r}"
            )
        images.append(image)
        if i == len(lines):
            break
        points = lines[i]
        if _POINTS2D.fullmatch(points) and len(points.split()) % 3 == 0:
            i += 1  # X Y POINT3D_ID triples (not needed here)
        elif _image_line(points.strip(), path, i + 1) is None:
            raise SceneInputError(
                path, f"line {i + 1}",
                f"expected the POINTS2D line of image {image.image_id} (X Y POINT3D_ID triples), "
                f"got {points[:80]!r}",
            )
    return images


def _read_points_txt(path: Path) -> SparsePoints:
    xyz, rgb, error = [], [], []
    for number, line in _data_lines(path):
        tokens = line.split()
        try:
            if len(tokens) < 8 or len(tokens) % 2:
                raise ValueError
            point = (float(tokens[1]), float(tokens[2]), float(tokens[3]))
            colour = (int(tokens[4]), int(tokens[5]), int(tokens[6]))
            err = float(tokens[7])
            if not (0 <= colour[0] <= 255 and 0 <= colour[1] <= 255 and 0 <= colour[2] <= 255):
                raise ValueError
        except ValueError:
            raise SceneInputError(
                path, f"line {number}", "expected POINT3D_ID X Y Z R G B (0..255) ERROR, then "
                f"(IMAGE_ID POINT2D_IDX) pairs, got {line[:80]!r}",
            ) from None
        xyz.append(point)
        rgb.append(colour)
        error.append(err)
    return SparsePoints(
        xyz=np.asarray(xyz, dtype=np.float64).reshape(-1, 3),
        rgb=np.asarray(rgb, dtype=np.uint8).reshape(-1, 3),
        error=np.asarray(error, dtype=np.float64),
    )


def _format(values) -> str:
    return " ".join(repr(float(v)) for v in values)  # shortest text that reads back exactly


def _text_files(intrinsics: list[_Intrinsics], images: list[_Image], xyz, rgb) -> list[bytes]:
    cams = ["# Camera list with one line of data per camera:",
            "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
            f"# Number of cameras: {len(intrinsics)}"]
    cams += [f"{c.camera_id} {c.model} {c.width} {c.height} {_format(c.params)}" for c in intrinsics]
    imgs = ["# Image list with two lines of data per image:",
            "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
            "#   POINTS2D[] as (X, Y, POINT3D_ID)",
            f"# Number of images: {len(images)}, mean observations per image: 0"]
    for im in images:
        imgs += [f"{im.image_id} {_format(im.qvec)} {_format(im.tvec)} {im.camera_id} {im.name}", ""]
    pts = ["# 3D point list with one line of data per point:",
           "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
           f"# Number of points: {len(xyz)}, mean track length: 0"]
    pts += [f"{k} {x!r} {y!r} {z!r} {r} {g} {b} 0.0"
            for k, ((x, y, z), (r, g, b)) in enumerate(zip(xyz.tolist(), rgb.tolist()), start=1)]
    return [("\n".join(lines) + "\n").encode("utf-8") for lines in (cams, imgs, pts)]


# --- binary format (little-endian, as COLMAP writes it) ----------------------------------

_COUNT = struct.Struct("<Q")
_CAMERA = struct.Struct("<IiQQ")        # camera_id, model_id, width, height; then params
_IMAGE = struct.Struct("<I4d3dI")       # image_id, qvec, tvec, camera_id; then name\0
_POINT = struct.Struct("<Q3d3BdQ")      # point3D_id, xyz, rgb, error, track length
_POINT_DTYPE = np.dtype([("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3), ("error", "<f8"), ("track", "<u8")])


class _Bytes:
    """A read cursor over a binary file that reports truncation as a ``SceneInputError``."""

    def __init__(self, path: Path):
        self.path = path
        self.data = path.read_bytes()
        self.pos = 0

    def _need(self, size: int, field: str) -> None:
        if self.pos + size > len(self.data):
            raise SceneInputError(
                self.path, field,
                f"file ends at byte {len(self.data)}, {self.pos + size - len(self.data)} bytes short "
                "(truncated or garbled file)",
            )

    def take(self, layout: struct.Struct, field: str) -> tuple:
        self._need(layout.size, field)
        out = layout.unpack_from(self.data, self.pos)
        self.pos += layout.size
        return out

    def skip(self, size: int, field: str) -> None:
        self._need(size, field)
        self.pos += size

    def count(self, record_size: int, field: str) -> int:
        """A uint64 record count, checked against the bytes left (each record >= record_size)."""
        (n,) = self.take(_COUNT, field)
        if n * record_size > len(self.data) - self.pos:
            raise SceneInputError(
                self.path, field, f"{n} records cannot fit in the {len(self.data) - self.pos} bytes left "
                "(truncated or garbled file)",
            )
        return n

    def name(self, field: str) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise SceneInputError(self.path, field, "file ends inside the name (truncated or garbled file)")
        raw, self.pos = self.data[self.pos:end], end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise SceneInputError(self.path, field, f"name {raw[:40]!r} is not UTF-8 (garbled file?)") from None

    def finish(self) -> None:
        if self.pos != len(self.data):
            raise SceneInputError(
                self.path, None,
                f"{len(self.data) - self.pos} unexpected bytes after the last record (garbled file)",
            )


def _read_cameras_bin(path: Path) -> dict[int, _Intrinsics]:
    f = _Bytes(path)
    out: dict[int, _Intrinsics] = {}
    for k in range(f.count(_CAMERA.size, "number of cameras")):
        camera_id, model_id, width, height = f.take(_CAMERA, f"camera record {k}")
        where = f"camera {camera_id}"
        if not 0 <= model_id < len(MODEL_NAMES):
            raise SceneInputError(path, where, f"unknown camera model id {model_id} "
                                  f"(supported: {', '.join(SUPPORTED_MODELS)}; garbled file?)")
        model = MODEL_NAMES[model_id]
        if model not in _PARAMS:
            raise _unsupported(path, camera_id, model)
        params = list(f.take(struct.Struct(f"<{len(_PARAMS[model])}d"), f"{where}: params"))
        if camera_id in out:
            raise SceneInputError(path, where, "defined twice")
        out[camera_id] = _checked_intrinsics(path, where, camera_id, model, width, height, params)
    f.finish()
    return out


def _read_images_bin(path: Path) -> list[_Image]:
    f = _Bytes(path)
    images = []
    for k in range(f.count(_IMAGE.size + 1 + _COUNT.size, "number of images")):
        image_id, *values, camera_id = f.take(_IMAGE, f"image record {k}")
        where = f"image {image_id}"
        name = f.name(f"{where}: name")
        (n_points,) = f.take(_COUNT, f"{where}: number of points2D")
        f.skip(24 * n_points, f"{where}: points2D")  # X, Y (double) and POINT3D_ID (uint64)
        if not np.all(np.isfinite(values[4:])):
            raise SceneInputError(path, where, f"translation {values[4:]} (expected finite values)")
        images.append(_Image(image_id, _normalized_qvec(values[:4], path, where), np.asarray(values[4:]),
                             camera_id, name))
    f.finish()
    return images


def _read_images(path: Path) -> list[_Image]:
    images = _read_images_bin(path) if path.suffix == ".bin" else _read_images_txt(path)
    ids = [im.image_id for im in images]
    if len(set(ids)) != len(ids):
        dup = next(i for i in ids if ids.count(i) > 1)
        raise SceneInputError(path, f"image {dup}", "defined twice")
    return images


def _read_points_bin(path: Path) -> SparsePoints:
    f = _Bytes(path)
    n = f.count(_POINT.size, "number of points")
    xyz, rgb, error = np.empty((n, 3)), np.empty((n, 3), np.uint8), np.empty(n)
    for k in range(n):
        point_id, x, y, z, r, g, b, err, track = f.take(_POINT, f"point record {k}")
        f.skip(8 * track, f"point {point_id}: track")  # (IMAGE_ID, POINT2D_IDX) uint32 pairs
        xyz[k], rgb[k], error[k] = (x, y, z), (r, g, b), err
    f.finish()
    return SparsePoints(xyz=xyz, rgb=rgb, error=error)


def _binary_files(intrinsics: list[_Intrinsics], images: list[_Image], xyz, rgb) -> list[bytes]:
    cams = [_COUNT.pack(len(intrinsics))]
    for c in intrinsics:
        cams.append(_CAMERA.pack(c.camera_id, MODEL_NAMES.index(c.model), c.width, c.height))
        cams.append(struct.pack(f"<{len(c.params)}d", *c.params))
    imgs = [_COUNT.pack(len(images))]
    for im in images:
        imgs.append(_IMAGE.pack(im.image_id, *im.qvec, *im.tvec, im.camera_id))
        imgs.append(im.name.encode("utf-8") + b"\0" + _COUNT.pack(0))
    pts = np.zeros(len(xyz), dtype=_POINT_DTYPE)
    pts["id"], pts["xyz"], pts["rgb"] = np.arange(1, len(xyz) + 1), xyz, rgb
    return [b"".join(cams), b"".join(imgs), _COUNT.pack(len(xyz)) + pts.tobytes()]


# --- writing -----------------------------------------------------------------------------


def _write(sparse_dir: Path, cameras: list[Camera], points, colors, *, binary: bool) -> None:
    if not binary:
        shadowing = [f"{s}.bin" for s in STEMS if (sparse_dir / f"{s}.bin").exists()]
        if shadowing:  # the reader prefers .bin, so a text model here would never be read
            raise ValueError(f"{sparse_dir} holds {', '.join(shadowing)}, which would shadow a text model")

    intrinsics: dict[tuple, _Intrinsics] = {}
    images: list[_Image] = []
    for image_id, camera in enumerate(sort_by_name(list(cameras)), start=1):
        _check_name(camera.name)
        if images and images[-1].name == camera.name:
            raise ValueError(f"camera name {camera.name!r} appears twice (expected unique names)")
        model, params = _model_params(camera)
        key = (model, int(camera.width), int(camera.height), params)
        if key not in intrinsics:
            intrinsics[key] = _Intrinsics(len(intrinsics) + 1, *key)
        qvec, tvec = _pose(camera)
        images.append(_Image(image_id, qvec, tvec, intrinsics[key].camera_id, camera.name))

    xyz = np.zeros((0, 3)) if points is None else np.asarray(points, dtype=np.float64).reshape(-1, 3)
    rgb = np.full(xyz.shape, _GREY, np.uint8) if colors is None else np.asarray(colors)
    if rgb.shape != xyz.shape:
        raise ValueError(f"colors shape {rgb.shape} does not match points shape {xyz.shape}")
    make = _binary_files if binary else _text_files
    contents = make(list(intrinsics.values()), images, xyz, rgb.astype(np.uint8))
    ext = ".bin" if binary else ".txt"
    write_files(sparse_dir, {f"{stem}{ext}": data for stem, data in zip(STEMS, contents)})
