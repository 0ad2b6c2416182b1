"""The demo is the whole job: on the tiny preset it writes the converted scene, the video,
the stills and a summary (slow: synthesis, conversion and a rollout, ~80 s on 2 cores)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from phirie_jax.demo import run_demo

pytestmark = pytest.mark.slow


def test_demo_writes_scene_video_stills_and_summary(tmp_path):
    result = run_demo(tmp_path, preset="tiny", seed=1)
    media = tmp_path / "media"
    stills = {name: cv2.imread(str(media / f"{name}.png")) for name in ("before", "after_conversion", "after_shot")}
    assert all(img is not None for img in stills.values())
    # the shot moved something: the last frame differs from the first
    assert np.abs(stills["after_shot"].astype(int) - stills["after_conversion"].astype(int)).mean() > 0.5
    video = cv2.VideoCapture(str(media / "rollout.mp4"))
    frames = 0
    while video.read()[0]:
        frames += 1
    assert frames > 10
    manifest = result["manifest"]
    assert manifest["background"]["filled"] > 0
    assert {"synthesize", "convert", "rollout"} <= set(result["timings"])
    assert all(p["psnr_db"] > 40 for p in result["previews"])  # the written images are our renders
    scores = result["background_scores"]  # the targets, in the rollout camera
    assert scores["region_px"] > 0 and scores["uncovered"] >= 25.0 and scores["outside"] >= 40.0, scores
