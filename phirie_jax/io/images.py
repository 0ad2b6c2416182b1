"""Image sizes from file headers, so images can be checked against cameras without decoding.

PNG and JPEG headers are parsed here (the IHDR chunk; the first SOFn marker); any
other format falls back to a full OpenCV decode. The size is the stored size: EXIF
orientation is not applied, which is how COLMAP and the 3DGS training loaders see
the pixels the cameras were calibrated on.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from phirie_jax.errors import SceneInputError

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# SOF0..SOF15 carry the frame size; 0xC4 (DHT), 0xC8 (JPG) and 0xCC (DAC) share the range.
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
# Markers without a length field: TEM, RST0..7, SOI, EOI.
_JPEG_STANDALONE = frozenset([0x01, *range(0xD0, 0xD8), 0xD8, 0xD9])


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) in pixels of the image at ``path``, read from its header.

    Raises ``SceneInputError`` when the file is missing, unreadable or not an image.
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(len(_PNG_SIGNATURE))
            if head == _PNG_SIGNATURE:
                return _png_size(f, path)
            if head[:2] == b"\xff\xd8":
                size = _jpeg_size(f, path)
                if size is not None:
                    return size
    except FileNotFoundError:
        raise SceneInputError(path, None, "image file not found") from None
    except IsADirectoryError:
        raise SceneInputError(path, None, "expected an image file, found a folder") from None
    except OSError as e:
        raise SceneInputError(path, None, f"cannot read image ({e.strerror or e})") from None
    return _decoded_size(path)


def _png_size(f, path: Path) -> tuple[int, int]:
    # The first chunk must be IHDR: length (4), type (4), width (4), height (4), ...
    chunk = f.read(16)
    if len(chunk) < 16 or chunk[4:8] != b"IHDR":
        raise SceneInputError(path, "PNG header", "truncated or missing IHDR chunk")
    width, height = struct.unpack(">II", chunk[8:16])
    if width == 0 or height == 0:
        raise SceneInputError(path, "PNG header", f"image size {width}x{height} (expected positive)")
    return int(width), int(height)


def _jpeg_size(f, path: Path) -> tuple[int, int] | None:
    """Walk the marker segments after SOI up to the first SOFn.

    Returns None when the frame header defers its height to a DNL marker (height 0),
    so the caller decodes instead.
    """
    f.seek(2)
    while True:
        byte = f.read(1)
        if not byte:
            raise SceneInputError(path, "JPEG header", "file ends before a frame (SOFn) marker")
        if byte != b"\xff":
            raise SceneInputError(path, "JPEG header", f"expected a marker at byte {f.tell() - 1}")
        marker = f.read(1)
        while marker == b"\xff":  # fill bytes may precede a marker
            marker = f.read(1)
        if not marker:
            raise SceneInputError(path, "JPEG header", "file ends inside a marker")
        code = marker[0]
        if code in _JPEG_STANDALONE:
            if code == 0xD9:
                raise SceneInputError(path, "JPEG header", "end of image before a frame (SOFn) marker")
            continue
        raw = f.read(2)
        if len(raw) < 2:
            raise SceneInputError(path, "JPEG header", "file ends inside a segment length")
        (length,) = struct.unpack(">H", raw)
        if length < 2:
            raise SceneInputError(path, "JPEG header", f"segment length {length} (expected >= 2)")
        if code in _JPEG_SOF:
            body = f.read(5)  # precision (1), height (2), width (2)
            if len(body) < 5:
                raise SceneInputError(path, "JPEG header", "file ends inside the frame header")
            _, height, width = struct.unpack(">BHH", body)
            if height == 0:
                return None
            if width == 0:
                raise SceneInputError(path, "JPEG header", "frame width 0 (expected positive)")
            return int(width), int(height)
        f.seek(length - 2, 1)


def _decoded_size(path: Path) -> tuple[int, int]:
    import cv2  # only for formats whose header is not parsed here

    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as e:
        raise SceneInputError(path, None, f"cannot read image ({e.strerror or e})") from None
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION) if data.size else None
    if image is None:
        raise SceneInputError(path, None, "not a readable image (expected PNG, JPEG or a format OpenCV decodes)")
    return int(image.shape[1]), int(image.shape[0])
