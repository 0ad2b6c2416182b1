"""Image sizes from PNG / JPEG headers agree with a full OpenCV decode."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from phirie_jax.errors import SceneInputError
from phirie_jax.io.images import image_size


def _write(path, image) -> None:
    assert cv2.imwrite(str(path), image)


def _decoded(path) -> tuple[int, int]:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    return image.shape[1], image.shape[0]


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("channels", [1, 3, 4])
def test_png_header_matches_decode(tmp_path, dtype, channels):
    rng = np.random.default_rng(0)
    shape = (37, 53) if channels == 1 else (37, 53, channels)
    path = tmp_path / "image.png"
    _write(path, rng.integers(0, np.iinfo(dtype).max, shape, dtype=dtype))
    assert image_size(path) == (53, 37) == _decoded(path)


@pytest.mark.parametrize("progressive", [False, True])
def test_jpeg_header_matches_decode(tmp_path, progressive):
    rng = np.random.default_rng(1)
    path = tmp_path / "image.jpg"
    params = [cv2.IMWRITE_JPEG_PROGRESSIVE, int(progressive)]
    assert cv2.imwrite(str(path), rng.integers(0, 255, (41, 67, 3), dtype=np.uint8), params)
    assert image_size(path) == (67, 41) == _decoded(path)


def test_jpeg_with_leading_segments(tmp_path):
    """APPn / COM segments before the frame header are skipped by their lengths."""
    ok, encoded = cv2.imencode(".jpg", np.zeros((20, 30, 3), np.uint8))
    assert ok
    data = encoded.tobytes()
    comment = b"\xff\xfe" + (2 + 300).to_bytes(2, "big") + b"\xff" * 300  # 0xFF bytes inside a segment
    path = tmp_path / "commented.jpg"
    path.write_bytes(data[:2] + comment + data[2:])
    assert image_size(path) == (30, 20) == _decoded(path)


def test_other_formats_fall_back_to_decode(tmp_path):
    path = tmp_path / "image.bmp"
    _write(path, np.zeros((9, 14, 3), np.uint8))
    assert image_size(path) == (14, 9)


def test_bad_files_raise_scene_input_error(tmp_path):
    with pytest.raises(SceneInputError, match="not found"):
        image_size(tmp_path / "missing.png")

    garbage = tmp_path / "garbage.png"
    garbage.write_bytes(b"this is not an image at all")
    with pytest.raises(SceneInputError, match="garbage.png"):
        image_size(garbage)

    path = tmp_path / "image.png"
    _write(path, np.zeros((5, 5), np.uint8))
    truncated = tmp_path / "truncated.png"
    truncated.write_bytes(path.read_bytes()[:12])
    with pytest.raises(SceneInputError, match="truncated.png: PNG header"):
        image_size(truncated)

    jpeg = tmp_path / "image.jpg"
    _write(jpeg, np.zeros((5, 5, 3), np.uint8))
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(jpeg.read_bytes()[:30])  # ends inside the APP0 / quantisation segments
    with pytest.raises(SceneInputError, match="cut.jpg: JPEG header"):
        image_size(cut)
