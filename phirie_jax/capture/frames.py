"""The capture's pictures: a folder of photos, or the sharp frames of a video, at a working size.

Photos: every file in the folder (not its subfolders) with an image suffix, in name order,
decoded with OpenCV (which applies the EXIF orientation, so portrait photos are upright),
downscaled to ``FramesConfig.resolution`` on the longer side if larger, and written as PNG
(lossless) into the working folder under their own stem. They must share one size.

Video: the frames are scored by sharpness (the variance of the Laplacian of the grey image, at
most ``SHARPNESS_SIDE`` pixels on its longer side, so the score does not depend on the video's
resolution); the video is cut into ``FramesConfig.frames`` stretches of equal length and the
sharpest frame of each is kept (named by its frame number). Motion blur scores low, so a
hand-held sweep keeps its steady moments.

One camera: photos whose EXIF names one camera (make, model, focal length), or none, share one
set of intrinsics in the structure from motion; several cameras get one set per photo.
"""

from __future__ import annotations

import dataclasses
import itertools
import shutil
from pathlib import Path

import numpy as np

from phirie_jax.capture.config import IMAGE_SUFFIXES, VIDEO_SUFFIXES, FramesConfig
from phirie_jax.errors import SceneInputError
from phirie_jax.io.atomic import write_bytes
from phirie_jax.progress import task

SHARPNESS_SIDE = 640   # px: sharpness is measured on the grey frame downscaled to this longer side
EXIF_MAKE, EXIF_MODEL, EXIF_IFD, EXIF_FOCAL = 0x010F, 0x0110, 0x8769, 0x920A


@dataclasses.dataclass(frozen=True)
class Frames:
    """The pictures the structure from motion and the training see."""

    folder: Path             # one PNG per picture
    names: tuple[str, ...]   # file names in ``folder``, in order
    width: int
    height: int
    video: bool              # frames of a video (matched sequentially) or photos (exhaustively)
    one_camera: bool         # one set of intrinsics for all (EXIF: one camera, or none)
    record: dict             # what was read and kept

    def as_json(self) -> dict:
        return {"folder": str(self.folder), "names": list(self.names), "width": self.width, "height": self.height,
                "video": self.video, "one_camera": self.one_camera, "record": self.record}

    @staticmethod
    def from_json(data: dict) -> Frames:
        return Frames(Path(data["folder"]), tuple(data["names"]), data["width"], data["height"], data["video"],
                      data["one_camera"], data["record"])


def is_video(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES


def sharpness(grey: np.ndarray) -> float:
    """Variance of the Laplacian of a grey image (H, W) uint8, measured at most ``SHARPNESS_SIDE`` px wide."""
    import cv2

    grey = downscaled(grey, SHARPNESS_SIDE)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def sharpest_per_stretch(scores: np.ndarray, count: int) -> np.ndarray:
    """Indices of the best score in each of ``count`` equal stretches of ``scores`` (S,), increasing.
    All indices when there are no more scores than stretches."""
    if len(scores) <= count:
        return np.arange(len(scores))
    edges = np.linspace(0, len(scores), count + 1).round().astype(int)
    return np.array([lo + int(np.argmax(scores[lo:hi])) for lo, hi in itertools.pairwise(edges)])


def downscaled(image: np.ndarray, longest: int) -> np.ndarray:
    """The image shrunk (area interpolation) so its longer side is at most ``longest`` pixels."""
    import cv2

    h, w = image.shape[:2]
    factor = longest / max(h, w)
    if factor >= 1.0:
        return image
    return cv2.resize(image, (max(1, round(w * factor)), max(1, round(h * factor))), interpolation=cv2.INTER_AREA)


def _write_png(path: Path, image: np.ndarray) -> None:
    import cv2

    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise RuntimeError(f"PNG encoding failed for {path}")
    write_bytes(path, buf.tobytes())


def exif_camera(path: Path) -> tuple | None:
    """(make, model, focal length) from a photo's EXIF, or None when it has none."""
    try:
        from PIL import Image

        with Image.open(path) as im:
            exif = im.getexif()
            focal = exif.get_ifd(EXIF_IFD).get(EXIF_FOCAL)
            key = (exif.get(EXIF_MAKE), exif.get(EXIF_MODEL), None if focal is None else float(focal))
    except (OSError, ValueError, TypeError, ImportError):  # no EXIF, or a format PIL cannot read
        return None
    return None if key == (None, None, None) else key


def list_photos(folder: Path) -> list[Path]:
    """Files of ``folder`` with an image suffix, in name order."""
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def _too_few(where: Path, count: int, config: FramesConfig, what: str) -> SceneInputError:
    return SceneInputError(where, None, f"{count} {what} (expected at least {config.min_images}; a capture wants "
                           "20 or more, each part of the scene in three or more of them)")


def photo_frames(folder: Path, config: FramesConfig, out: Path) -> Frames:
    """Photos of ``folder`` → PNGs in ``out`` (module docstring)."""
    import cv2

    photos = list_photos(folder)
    if len(photos) < config.min_images:
        raise _too_few(folder, len(photos), config, f"pictures ({', '.join(IMAGE_SUFFIXES)})")
    stems = {}
    for p in photos:
        if p.stem in stems:
            raise SceneInputError(p, None, f"has the name of {stems[p.stem].name} but another suffix "
                                  "(expected one picture per name)")
        stems[p.stem] = p
    decoded, original = [], None
    for p in photos:  # every picture is checked before anything is written
        image = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if image is None:
            raise SceneInputError(p, None, "cannot be read as an image (expected a JPEG, PNG, TIFF, BMP or WebP "
                                  "picture; remove it or replace it)")
        original = original or [image.shape[1], image.shape[0]]
        decoded.append(downscaled(image, config.resolution))
    sizes = [(im.shape[1], im.shape[0]) for im in decoded]
    if len(set(sizes)) != 1:
        other = next(i for i, s in enumerate(sizes) if s != sizes[0])
        raise SceneInputError(photos[other], None, f"is {sizes[other][0]}×{sizes[other][1]} after orientation and "
                              f"downscaling, {photos[0].name} {sizes[0][0]}×{sizes[0][1]} (expected pictures of one "
                              "size: rotate or crop them alike)")
    out.mkdir(parents=True, exist_ok=True)
    names = []
    with task("writing the pictures", len(photos)) as advance:
        for p, image in zip(photos, decoded):
            names.append(p.stem + ".png")
            _write_png(out / names[-1], image)
            advance()
    cameras = {exif_camera(p) for p in photos}
    w, h = sizes[0]
    return Frames(out, tuple(names), w, h, video=False, one_camera=len(cameras) == 1,
                  record={"source": str(folder), "pictures": len(photos), "original_size": original,
                          "exif_cameras": len(cameras - {None}), "one_camera": len(cameras) == 1})


def video_frames(path: Path, config: FramesConfig, out: Path) -> Frames:
    """``config.frames`` sharp frames of the video at ``path`` → PNGs in ``out`` (module docstring)."""
    import cv2

    def opened():
        capture = cv2.VideoCapture(str(path))
        if not capture.isOpened():
            raise SceneInputError(path, None, "cannot be read as a video (expected a video OpenCV can decode: "
                                  "MP4/H.264, MOV, AVI, MKV, WebM)")
        return capture

    capture, scores = opened(), []
    total = int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) or None
    with task("scoring the video's frames", total) as advance:
        while True:
            ok, frame = capture.read()
            if not ok:
                break
            scores.append(sharpness(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)))
            advance()
    capture.release()
    if len(scores) < config.min_images:
        raise _too_few(path, len(scores), config, "frames in the video")
    keep = sharpest_per_stretch(np.asarray(scores), config.frames)
    wanted, names = set(keep.tolist()), []
    out.mkdir(parents=True, exist_ok=True)
    capture, index, size = opened(), 0, None
    with task("writing the sharpest frames", len(keep)) as advance:
        while wanted:
            ok, frame = capture.read()
            if not ok:
                break
            if index in wanted:
                frame = downscaled(frame, config.resolution)
                size = (frame.shape[1], frame.shape[0])
                names.append(f"frame_{index:06d}.png")
                _write_png(out / names[-1], frame)
                wanted.discard(index)
                advance()
            index += 1
    capture.release()
    if wanted or size is None:
        raise SceneInputError(path, None, "the video ended before frames it counted (expected a readable video; "
                              "re-encode it, e.g. ffmpeg -i IN -c:v libx264 OUT.mp4)")
    chosen = np.asarray(scores)[keep]
    return Frames(out, tuple(names), size[0], size[1], video=True, one_camera=True,
                  record={"source": str(path), "video_frames": len(scores), "kept": len(names),
                          "frame_numbers": keep.tolist(), "sharpness_kept_median": round(float(np.median(chosen)), 2),
                          "sharpness_all_median": round(float(np.median(scores)), 2)})


def prepare_frames(source: Path, config: FramesConfig, out: Path) -> Frames:
    """The pictures of ``source`` (a folder of photos or a video file) written into ``out``."""
    source = Path(source)
    if out.exists():
        shutil.rmtree(out)
    if is_video(source):
        return video_frames(source, config, out)
    if source.is_dir():
        return photo_frames(source, config, out)
    if not source.exists():
        raise SceneInputError(source, None, "not found (expected a folder of photos or a video file)")
    raise SceneInputError(source, None, f"is neither a folder of photos nor a video (expected a folder, or a file "
                          f"ending in {', '.join(VIDEO_SUFFIXES)})")
