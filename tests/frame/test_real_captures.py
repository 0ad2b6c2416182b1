"""The frame of the real captures against their hand-found truth (``tests/fixtures/frame_truth.json``):
up within 5° of the true support normal (gravity), the true scale inside the stated band, and a
frame that says where its scale comes from. Skipped without ``../shared/data``."""

from __future__ import annotations

import numpy as np
import pytest

from phirie_jax.frame import estimate
from phirie_jax.frame.resolve import resolve_frame
from phirie_jax.io.scene import load_scene
from tests.conftest import shared_data
from tests.frame.capture_truth import derive, load_truth

CAPTURES = ("snowmiku", "fox")


@pytest.fixture(scope="module")
def truth():
    return load_truth()


@pytest.fixture(scope="module", params=CAPTURES)
def capture(request, truth):
    scene = load_scene(shared_data("captures", request.param))
    return request.param, scene, truth[request.param]


def test_the_truth_is_what_its_picks_say(capture, truth):
    """The stored truth is recomputed from the picks it keeps (and the picks agree with each
    other: points clicked in several photos meet within a few pixels)."""
    name, scene, record = capture
    cameras = {c.name: c for c in scene.cameras}
    found = derive(name, cameras, truth, estimate.cameras_up(scene.cameras))
    assert estimate.angle_deg(found["up"], np.asarray(record["up"])) < 0.01
    assert found["scale"] == pytest.approx(record["scale"], rel=1e-3)
    assert found["scale_range"] == pytest.approx(record["scale_range"], rel=1e-3)
    if name == "snowmiku":  # the floor's edge under the wardrobe is level in the truth's up
        from tests.frame.capture_truth import line

        _, direction = line(cameras, record["horizontal_check"])
        assert abs(90.0 - estimate.angle_deg(direction, found["up"])) < 1.0


def test_up_and_scale_meet_the_truth(capture):
    name, scene, record = capture
    frame = resolve_frame(scene)
    error = estimate.angle_deg(frame.capture_up, np.asarray(record["up"]))
    assert error < record["up_tolerance_deg"], (name, error, frame.up_source)
    low, high = frame.scale / frame.scale_uncertainty, frame.scale * frame.scale_uncertainty
    assert low <= record["scale"] <= high, (name, frame.scale, frame.scale_uncertainty, record["scale"])
    # nothing measured the scale: the frame says it is a prior
    assert frame.scale_is_prior and frame.scale_source.startswith("prior: the cameras orbit a point")
    cues = {c["key"]: c for c in frame.evidence["cues"]}
    assert cues["plumb_lines"]["used"] and cues["camera_vote"]["used"]
    if name == "snowmiku":
        # the support is the duvet under the plush, found under the point the cameras look at;
        # soft and bunched, its plane leans: that is recorded and announced, up does not follow it
        support = frame.support
        assert support is not None and estimate.angle_deg(support.normal, np.array([0.0, 0.0, 1.0])) < 15.0
        assert frame.record()["support"]["source"] == support.source
    else:
        # a wall-mounted head: the wall is 90° from up, no support, and no warning about it
        assert frame.support is None and frame.record()["support"] is None
        assert all("wall" not in w for w in frame.warnings)
