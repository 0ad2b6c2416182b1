"""COLMAP sparse models: text and binary round trips, hand-written files, bad input."""

from __future__ import annotations

import dataclasses
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from phirie_jax.errors import SceneInputError
from phirie_jax.io.camera import intrinsics_matrix, outside_paths_allowed
from phirie_jax.io.colmap import (
    MODEL_NAMES,
    SUPPORTED_MODELS,
    _quaternion,
    _world_to_camera,
    read_colmap_model,
    read_colmap_points,
    write_colmap_binary,
    write_colmap_text,
)
from phirie_jax.io.transforms_json import read_transforms_json, write_transforms_json
from phirie_jax.types import Camera

POSE_TOL = 1e-12
DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
WRITERS = {"txt": write_colmap_text, "bin": write_colmap_binary}


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """(3, 3) rotation from a random unit quaternion."""
    w, x, y, z = rng.normal(size=4)
    n = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def pose(rot: np.ndarray, t) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, t
    return out


def model_camera(model: str, name: str, rng: np.random.Generator, rot: np.ndarray | None = None) -> Camera:
    """A camera whose intrinsics are exactly expressible in ``model``."""
    f, f2 = rng.uniform(300, 900, size=2)
    cx, cy = rng.uniform(100, 300, size=2)
    k1, k2, p1, p2 = rng.uniform(-0.1, 0.1, size=4)
    fy, distortion = {
        "SIMPLE_PINHOLE": (f, []),
        "PINHOLE": (f2, []),
        "SIMPLE_RADIAL": (f, [k1, 0.0, 0.0, 0.0]),
        "RADIAL": (f, [k1, k2, 0.0, 0.0]),
        "OPENCV": (f2, [k1, k2, p1, p2]),
    }[model]
    rot = random_rotation(rng) if rot is None else rot
    return Camera(
        name=name, K=intrinsics_matrix(f, fy, cx, cy), world_to_camera=pose(rot, rng.normal(size=3)),
        width=int(rng.integers(200, 800)), height=int(rng.integers(200, 600)), model=model,
        distortion=np.asarray(distortion, dtype=np.float64),
    )


def assert_same_cameras(read: list[Camera], written: list[Camera]) -> None:
    assert [c.name for c in read] == sorted(c.name for c in written)
    by_name = {c.name: c for c in written}
    for camera in read:
        expected = by_name[camera.name]
        np.testing.assert_array_equal(camera.K, expected.K)
        np.testing.assert_allclose(camera.world_to_camera, expected.world_to_camera, rtol=0, atol=POSE_TOL)
        assert (camera.width, camera.height, camera.model) == (expected.width, expected.height, expected.model)
        np.testing.assert_array_equal(camera.distortion, expected.distortion)
        assert camera.K.dtype == camera.world_to_camera.dtype == np.float64


# --- round trips ---------------------------------------------------------------------------


@pytest.mark.parametrize("fmt", ["txt", "bin"])
def test_round_trip_all_models(tmp_path, fmt):
    rng = np.random.default_rng(7)
    half_turns = [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]
    cameras = [model_camera(m, f"{m.lower()} view {i}.png", rng) for i, m in enumerate(SUPPORTED_MODELS)]
    # Rotations by 180° (quaternion w = 0) and a second image sharing intrinsics.
    cameras += [model_camera("OPENCV", f"half turn {i}.jpg", rng, rot) for i, rot in enumerate(half_turns)]
    cameras.append(dataclasses.replace(cameras[0], name="a shared.png"))
    points = rng.normal(size=(25, 3))
    colors = rng.integers(0, 256, size=(25, 3), dtype=np.uint8)

    WRITERS[fmt](tmp_path, cameras[::-1], points, colors)
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"{s}.{fmt}" for s in ("cameras", "images", "points3D")]

    read, xyz = read_colmap_model(tmp_path)
    assert_same_cameras(read, cameras)
    np.testing.assert_array_equal(xyz, points)
    sparse = read_colmap_points(tmp_path)
    np.testing.assert_array_equal(sparse.rgb, colors)
    assert sparse.xyz.shape == (25, 3) and sparse.error.shape == (25,)
    assert _num_colmap_cameras(tmp_path, fmt) == len(cameras) - 1  # one per distinct intrinsics


def _num_colmap_cameras(folder: Path, fmt: str) -> int:
    if fmt == "bin":
        return struct.unpack("<Q", (folder / "cameras.bin").read_bytes()[:8])[0]
    lines = (folder / "cameras.txt").read_text().splitlines()
    return sum(1 for line in lines if line and not line.startswith("#"))


def test_unrepresentable_model_falls_back_to_pinhole_or_opencv(tmp_path):
    rng = np.random.default_rng(3)
    distorted = model_camera("OPENCV", "a.png", rng)
    plain = model_camera("PINHOLE", "b.png", rng)
    cameras = [
        dataclasses.replace(distorted, model="SIMPLE_RADIAL"),  # fx != fy, p1 != 0: not SIMPLE_RADIAL
        dataclasses.replace(plain, model="SIMPLE_PINHOLE"),     # fx != fy: not SIMPLE_PINHOLE
    ]
    write_colmap_text(tmp_path, cameras)
    read, _ = read_colmap_model(tmp_path)
    assert [c.model for c in read] == ["OPENCV", "PINHOLE"]
    np.testing.assert_array_equal(read[0].K, distorted.K)
    np.testing.assert_array_equal(read[0].distortion, distorted.distortion)


def test_points_are_optional_and_image_dir_sets_paths(tmp_path):
    rng = np.random.default_rng(4)
    write_colmap_binary(tmp_path, [model_camera("PINHOLE", "x.png", rng)])
    assert read_colmap_model(tmp_path)[1].shape == (0, 3)
    (tmp_path / "points3D.bin").unlink()
    cameras, points = read_colmap_model(tmp_path, image_dir=tmp_path / "images")
    assert points is None and read_colmap_points(tmp_path) is None
    assert cameras[0].image_path == tmp_path / "images" / "x.png"


@pytest.mark.parametrize("name", ["../../etc/hostname", "/etc/hostname"])
def test_an_image_name_outside_the_image_folder_is_refused(tmp_path, name):
    """COLMAP names are relative to the image folder: one leading out of it (``..`` or absolute)
    is refused with one line unless ``outside_paths_allowed``."""
    rng = np.random.default_rng(5)
    write_colmap_text(tmp_path, [model_camera("PINHOLE", "x.png", rng)])
    text = (tmp_path / "images.txt").read_text().replace(" x.png", f" {name}")
    (tmp_path / "images.txt").write_text(text)
    with pytest.raises(SceneInputError) as err:
        read_colmap_model(tmp_path, image_dir=tmp_path / "images")
    assert str(err.value) == (f"{tmp_path / 'images.txt'}: image 1: name: {name!r} is outside {tmp_path / 'images'} "
                              "(expected an image inside the scene folder; --allow-outside-paths reads it anyway)")
    assert read_colmap_model(tmp_path)[0][0].name == name  # no image folder given: nothing to open
    with outside_paths_allowed():
        assert read_colmap_model(tmp_path, image_dir=tmp_path / "images")[0][0].name == name


def test_binary_is_preferred_and_text_never_shadowed(tmp_path):
    rng = np.random.default_rng(5)
    write_colmap_text(tmp_path, [model_camera("PINHOLE", "text.png", rng)])
    write_colmap_binary(tmp_path, [model_camera("PINHOLE", "binary.png", rng)])
    assert [c.name for c in read_colmap_model(tmp_path)[0]] == ["binary.png"]
    with pytest.raises(ValueError, match="shadow"):
        write_colmap_text(tmp_path, [model_camera("PINHOLE", "text.png", rng)])


def test_failed_write_leaves_nothing(tmp_path):
    rng = np.random.default_rng(6)
    good = model_camera("PINHOLE", "a.png", rng)
    sheared = dataclasses.replace(good, name="b.png", world_to_camera=np.diag([1.0, 2.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="rigid"):
        write_colmap_binary(tmp_path / "model", [good, sheared])
    assert not (tmp_path / "model").exists() or not any((tmp_path / "model").iterdir())
    write_colmap_binary(tmp_path / "model", [good])
    assert sorted(p.name for p in (tmp_path / "model").iterdir()) == ["cameras.bin", "images.bin", "points3D.bin"]


def axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` about ``axis`` (Rodrigues)."""
    k = axis / np.linalg.norm(axis)
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


@settings(max_examples=200, deadline=None)
@given(
    axis=st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda a: np.linalg.norm(a) > 0.1),
    angle=st.one_of(st.floats(0, np.pi), st.floats(np.pi - 1e-4, np.pi), st.floats(0, 1e-6)),
)
def test_quaternion_round_trip_near_identity_and_half_turn(axis, angle):
    """R → qvec → R stays at float precision for every branch of the extraction."""
    rot = axis_angle(np.asarray(axis), angle)
    q = _quaternion(rot)
    assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-15
    np.testing.assert_allclose(_world_to_camera(q, np.zeros(3))[:3, :3], rot, rtol=0, atol=POSE_TOL)


# --- hand-written text ---------------------------------------------------------------------


def write_text_model(folder: Path, cameras: str, images: str, points: str | None = None) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "cameras.txt").write_text(cameras)
    (folder / "images.txt").write_text(images)
    if points is not None:
        (folder / "points3D.txt").write_text(points)


def test_camera_at_z5_looking_at_origin(tmp_path):
    """Hand-computed: centre (0, 0, 5), optical axis −z, image up = world +y.

    OpenCV axes in world terms: x_c = +x, y_c = −y, z_c = −z, so R = diag(1, −1, −1)
    (180° about x: qvec (0, 1, 0, 0)) and t = −R c = (0, 0, 5).
    """
    write_text_model(
        tmp_path,
        "1 PINHOLE 640 480 500 500 320 240\n",
        "1 0 1 0 0 0 0 5 1 cam.png\n\n",
    )
    (camera,), _ = read_colmap_model(tmp_path)
    np.testing.assert_allclose(camera.center, [0, 0, 5], atol=1e-15)
    uv, depth = camera.project(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]))
    np.testing.assert_allclose(uv[0], [320, 240])
    assert depth[0] == pytest.approx(5.0)
    assert uv[1, 0] > 320 and uv[2, 1] < 240  # world +x is image right, world +y is image up


def test_images_txt_points_lines_parsed_robustly(tmp_path):
    images = "\n".join([
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "3 1 0 0 0 0 0 0 1 third image.png",
        "1.5 2.5 -1 10.25 3e2 17",            # a POINTS2D line
        "1 0 2 0 0 1 2 3 1 first.png",        # quaternion not normalised: COLMAP normalises
        "",                                    # empty POINTS2D line
        "2 1 0 0 0 0 0 0 1 sub/dir/second.png",
        "4 1 0 0 0 0 0 0 1 no points line.png",  # POINTS2D line omitted ...
        "5 1 0 0 0 0 0 0 1 last.png",          # ... and at the end of the file
    ])
    write_text_model(tmp_path, "# c\n\n1 SIMPLE_PINHOLE 100 80 90 50 40\n", images)
    cameras, points = read_colmap_model(tmp_path)
    assert points is None
    assert [c.name for c in cameras] == ["first.png", "last.png", "no points line.png", "sub/dir/second.png",
                                         "third image.png"]
    np.testing.assert_allclose(cameras[0].world_to_camera[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-15)
    np.testing.assert_array_equal(cameras[0].world_to_camera[:3, 3], [1, 2, 3])


@pytest.mark.parametrize("model", [m for m in MODEL_NAMES if m not in SUPPORTED_MODELS])
def test_unsupported_model_in_text(tmp_path, model):
    write_text_model(tmp_path, f"1 PINHOLE 10 10 5 5 5 5\n7 {model} 640 480 1 2 3 4 5 6 7 8\n", "")
    with pytest.raises(SceneInputError) as err:
        read_colmap_model(tmp_path)
    message = str(err.value)
    assert "cameras.txt: camera 7" in message and model in message and "PINHOLE, SIMPLE_RADIAL" in message


@pytest.mark.parametrize("model_id", range(5, 11))
def test_unsupported_model_in_binary(tmp_path, model_id):
    write_colmap_binary(tmp_path, [model_camera("OPENCV", "a.png", np.random.default_rng(0))])
    data = bytearray((tmp_path / "cameras.bin").read_bytes())
    data[12:16] = struct.pack("<i", model_id)  # after the count (8) and camera_id (4)
    (tmp_path / "cameras.bin").write_bytes(bytes(data))
    with pytest.raises(SceneInputError) as err:
        read_colmap_model(tmp_path)
    assert "cameras.bin: camera 1" in str(err.value) and MODEL_NAMES[model_id] in str(err.value)


@pytest.mark.parametrize(
    "cameras, images, expected",
    [
        ("1 PINHOLE 640\n", "", "cameras.txt: line 1: expected CAMERA_ID MODEL WIDTH HEIGHT"),
        ("1 PINHOLE 640 480 500 500 320\n", "", "cameras.txt: line 1: PINHOLE has 4 parameters"),
        ("1 OPENCV 640 480 1 1 1 1 0 0 0\n", "", "OPENCV has 8 parameters"),
        ("1 PINHOLE 640 480 500 abc 320 240\n", "", "cameras.txt: line 1: PARAMS"),
        ("1 PINHOLE 0 480 500 500 320 240\n", "", "image size 0x480"),
        ("1 PINHOLE 640 480 500 500 320 240\n1 PINHOLE 640 480 5 5 3 2\n", "", "camera 1 defined twice"),
        ("1 PINHOLE 640 480 500 500 320 240\n", "1 1 0 0 0 0 0 0 1\n", "images.txt: line 1: expected IMAGE_ID"),
        ("1 PINHOLE 640 480 500 500 320 240\n", "1 0 0 0 0 0 0 0 1 a.png\n", "image 1: quaternion"),
        ("1 PINHOLE 640 480 500 500 320 240\n", "1 1 0 0 0 0 0 0 1 a.png\n1 2 3 4\n",
         "line 2: expected the POINTS2D"),
        ("1 PINHOLE 640 480 500 500 320 240\n", "12 1 0 0 0 0 0 0 7 a.png\n\n",
         "images.txt: image 12: camera_id 7 not in cameras.txt"),
        ("1 PINHOLE 640 480 500 500 320 240\n", "1 1 0 0 0 0 0 0 1 a.png\n\n2 1 0 0 0 0 0 0 1 a.png\n\n",
         "image 2: name 'a.png' repeats image 1"),
    ],
)
def test_bad_text_models(tmp_path, cameras, images, expected):
    write_text_model(tmp_path, cameras, images)
    with pytest.raises(SceneInputError) as err:
        read_colmap_model(tmp_path)
    assert expected in str(err.value)


def test_bad_points_text(tmp_path):
    write_text_model(tmp_path, "1 PINHOLE 10 10 5 5 5 5\n", "", "1 0 0 0 255 0 0 0.5\n2 0 0 0 256 0 0 0.5\n")
    with pytest.raises(SceneInputError, match="points3D.txt: line 2"):
        read_colmap_model(tmp_path)


def test_missing_files(tmp_path):
    with pytest.raises(SceneInputError, match="folder not found"):
        read_colmap_model(tmp_path / "nowhere")
    (tmp_path / "cameras.txt").write_text("")
    with pytest.raises(SceneInputError, match="images: missing"):
        read_colmap_model(tmp_path)


# --- damaged binary ------------------------------------------------------------------------


def _binary_model(folder: Path) -> None:
    rng = np.random.default_rng(11)
    cameras = [model_camera(m, f"view {i}.png", rng) for i, m in enumerate(SUPPORTED_MODELS)]
    write_colmap_binary(folder, cameras, rng.normal(size=(4, 3)))


@pytest.mark.parametrize("stem", ["cameras", "images", "points3D"])
def test_truncated_binary(tmp_path, stem):
    _binary_model(tmp_path)
    path = tmp_path / f"{stem}.bin"
    data = path.read_bytes()
    for cut in sorted({1, 8, 9, 30, len(data) // 2, len(data) - 1}):
        path.write_bytes(data[:cut])
        with pytest.raises(SceneInputError) as err:
            read_colmap_model(tmp_path)
        assert f"{stem}.bin" in str(err.value) and ("truncated" in str(err.value) or "garbled" in str(err.value))
    path.write_bytes(data + b"\0\0\0")
    with pytest.raises(SceneInputError, match="unexpected bytes"):
        read_colmap_model(tmp_path)


def test_garbled_binary_counts_and_model_ids(tmp_path):
    _binary_model(tmp_path)
    images = tmp_path / "images.bin"
    data = images.read_bytes()
    images.write_bytes(struct.pack("<Q", 10**12) + data[8:])
    with pytest.raises(SceneInputError, match="images.bin: number of images"):
        read_colmap_model(tmp_path)
    images.write_bytes(data)
    cameras = tmp_path / "cameras.bin"
    raw = bytearray(cameras.read_bytes())
    raw[12:16] = struct.pack("<i", 99)
    cameras.write_bytes(bytes(raw))
    with pytest.raises(SceneInputError, match="unknown camera model id 99"):
        read_colmap_model(tmp_path)


def test_unknown_camera_id_binary(tmp_path):
    write_colmap_binary(tmp_path, [model_camera("PINHOLE", "a.png", np.random.default_rng(2))])
    data = bytearray((tmp_path / "images.bin").read_bytes())
    data[8:12] = struct.pack("<I", 12)   # image_id
    data[68:72] = struct.pack("<I", 7)   # camera_id, after image_id (4), qvec (32) and tvec (24)
    (tmp_path / "images.bin").write_bytes(bytes(data))
    with pytest.raises(SceneInputError) as err:
        read_colmap_model(tmp_path)
    assert str(err.value).endswith("images.bin: image 12: camera_id 7 not in cameras.bin")


# --- real data -----------------------------------------------------------------------------

# Fractions of the 138,766 garden points that project inside each 648x420 image in
# front of its camera, measured at 0.5416, 0.4983 and 0.4323.
GARDEN_MIN_VISIBLE = (0.52, 0.48, 0.41)


@pytest.mark.skipif(not (DATA / "garden" / "test_garden.npz").exists(), reason="shared garden data absent")
def test_garden_cameras_in_all_formats(tmp_path):
    garden = np.load(DATA / "garden" / "test_garden.npz")
    width, height = int(garden["width"]), int(garden["height"])
    assert (width, height) == (648, 420)
    cameras = []
    for i, (view, K) in enumerate(zip(garden["viewmats"], garden["Ks"])):
        view = view.astype(np.float64)
        u, _, vt = np.linalg.svd(view[:3, :3])  # float32 storage: snap back onto a rotation
        view[:3, :3] = u @ vt
        cameras.append(Camera(f"frame_{i:05d}.jpg", K.astype(np.float64), view, width, height))
    points = garden["means3d"].astype(np.float64)

    write_colmap_text(tmp_path / "txt", cameras, points[::10], garden["colors"][::10])
    write_colmap_binary(tmp_path / "bin", cameras, points[::10], garden["colors"][::10])
    write_transforms_json(tmp_path / "transforms.json", cameras)
    formats = {
        "txt": read_colmap_model(tmp_path / "txt")[0],
        "bin": read_colmap_model(tmp_path / "bin")[0],
        "json": read_transforms_json(tmp_path / "transforms.json"),
    }
    np.testing.assert_array_equal(read_colmap_points(tmp_path / "txt").xyz, points[::10])
    np.testing.assert_array_equal(read_colmap_points(tmp_path / "bin").rgb, garden["colors"][::10])

    visible = {}
    for fmt, read in formats.items():
        assert_same_cameras(read, cameras)
        masks = []
        for camera in read:
            uv, depth = camera.project(points)
            inside = (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
            masks.append((depth > 0) & inside)
        visible[fmt] = np.stack(masks)
    for mask, bound in zip(visible["txt"], GARDEN_MIN_VISIBLE):
        assert mask.mean() >= bound
    np.testing.assert_array_equal(visible["txt"], visible["bin"])
    np.testing.assert_array_equal(visible["txt"], visible["json"])
