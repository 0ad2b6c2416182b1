"""The capture's pictures: a video gives its N sharpest frames, photos are checked and downscaled."""

from __future__ import annotations

import numpy as np
import pytest

from phirie_jax.capture.config import FramesConfig
from phirie_jax.capture.frames import prepare_frames, sharpest_per_stretch
from phirie_jax.errors import SceneInputError

VIDEO_FRAMES = 40
VIDEO_SIZE = (160, 120)


def _textured(rng, size=VIDEO_SIZE) -> np.ndarray:
    w, h = size
    tiles = rng.integers(0, 255, (-(-h // 8), -(-w // 8), 3), np.uint8)
    return np.ascontiguousarray(np.kron(tiles, np.ones((8, 8, 1), np.uint8))[:h, :w])


def _write_video(path, blurred: set[int]) -> None:
    """A VIDEO_FRAMES-frame MJPG video of a sliding checker texture; frames in ``blurred`` are motion-blurred."""
    import cv2

    rng = np.random.default_rng(0)
    base = _textured(rng, (VIDEO_SIZE[0] * 2, VIDEO_SIZE[1]))
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, VIDEO_SIZE)
    assert writer.isOpened()
    for i in range(VIDEO_FRAMES):
        frame = np.ascontiguousarray(base[:, i * 2:i * 2 + VIDEO_SIZE[0]])
        if i in blurred:
            frame = cv2.blur(frame, (15, 1))
        writer.write(frame)
    writer.release()


def test_sharpest_per_stretch_takes_the_best_of_each_equal_stretch():
    scores = np.array([1, 5, 2, 0, 9, 3, 4, 4, 1, 7], float)
    np.testing.assert_array_equal(sharpest_per_stretch(scores, 5), [1, 2, 4, 6, 9])  # ties: the first
    np.testing.assert_array_equal(sharpest_per_stretch(scores, 2), [4, 9])
    np.testing.assert_array_equal(sharpest_per_stretch(scores[:3], 8), [0, 1, 2])  # fewer frames than stretches


def test_a_video_yields_n_sharp_frames(tmp_path):
    import cv2

    video = tmp_path / "sweep.avi"
    blurred = {i for i in range(VIDEO_FRAMES) if i % 5 != 2}  # one sharp frame in every five
    _write_video(video, blurred)
    frames = prepare_frames(video, FramesConfig(frames=8, min_images=2), tmp_path / "frames")
    assert frames.video and len(frames.names) == 8 and (frames.width, frames.height) == VIDEO_SIZE
    numbers = frames.record["frame_numbers"]
    assert numbers == sorted(numbers) and all(n % 5 == 2 for n in numbers), numbers  # the sharp ones
    assert sorted(p.name for p in frames.folder.iterdir()) == sorted(frames.names)
    assert cv2.imread(str(frames.folder / frames.names[0])).shape == (VIDEO_SIZE[1], VIDEO_SIZE[0], 3)


def test_photos_are_downscaled_to_the_resolution(tmp_path):
    import cv2

    rng = np.random.default_rng(1)
    folder = tmp_path / "photos"
    folder.mkdir()
    for i in range(5):
        cv2.imwrite(str(folder / f"p{i}.jpg"), _textured(rng, (400, 300)))
    (folder / "notes.txt").write_text("not a picture")
    frames = prepare_frames(folder, FramesConfig(resolution=200), tmp_path / "frames")
    assert not frames.video and frames.one_camera
    assert frames.names == tuple(f"p{i}.png" for i in range(5)) and (frames.width, frames.height) == (200, 150)


@pytest.mark.parametrize("case", ["too few", "unreadable", "sizes"])
def test_bad_photos_are_one_error_naming_the_file(tmp_path, case):
    import cv2

    rng = np.random.default_rng(2)
    folder = tmp_path / "photos"
    folder.mkdir()
    for i in range(3 if case == "too few" else 6):
        cv2.imwrite(str(folder / f"p{i}.png"), _textured(rng, (160, 120) if case != "sizes" or i else (120, 160)))
    if case == "unreadable":
        (folder / "p3.png").write_bytes(b"\x89PNG\r\n\x1a\n not really")
    expected = {"too few": r"photos: 3 pictures .*expected at least 5", "unreadable": r"p3.png: cannot be read",
                "sizes": r"p1.png: is 160×120 .*p0.png 120×160"}[case]
    with pytest.raises(SceneInputError, match=expected):
        prepare_frames(folder, FramesConfig(), tmp_path / "frames")
