"""The scene frame on a synthetic tabletop copied into a tilted, scaled (×3.7), shifted frame:
up and metres are recovered (given, or estimated within the stated uncertainty), and moving a
capture into the world changes nothing a camera sees except depth units."""

from __future__ import annotations

import numpy as np
import pytest

from phirie_jax.frame import estimate, priors
from phirie_jax.frame.config import FrameConfig, scene_frame_config
from phirie_jax.frame.resolve import resolve_frame, scene_in_world, with_known_size
from phirie_jax.geometry import split_sim3
from phirie_jax.io.scene import load_scene
from phirie_jax.render import render
from tests.frame.conftest import UNITS_PER_METRE, WORLD_TO_CAPTURE


@pytest.fixture(scope="module")
def scenes(tilted_tabletop):
    return tilted_tabletop


def truth_to_world(frame) -> tuple[float, np.ndarray]:
    """(scale, rotation) of the map from the synthetic truth's frame to the resolved world."""
    scale, rotation, _ = split_sim3(frame.capture_to_world @ WORLD_TO_CAPTURE)
    return scale, rotation


def test_a_declared_metric_z_up_scene_is_left_as_it_is(scenes):
    scene = load_scene(scenes[0])
    frame = resolve_frame(scene, scene_frame_config(scenes[0]))
    assert frame.is_identity and frame.scale_source == "declared metric"
    assert frame.apply(scene) is scene


def test_given_scale_and_estimated_up(scenes):
    frame = resolve_frame(load_scene(scenes[1]), FrameConfig(scale=1 / UNITS_PER_METRE))
    scale, rotation = truth_to_world(frame)
    assert scale == pytest.approx(1.0, rel=1e-9)
    assert np.degrees(np.arccos(rotation[2, 2])) < 0.2          # truth's +z is the world's +z
    assert frame.up_source.startswith("support plane (") and frame.scale_source == "given (--scale)"


def test_estimated_scale_is_within_its_stated_uncertainty(scenes):
    frame = resolve_frame(load_scene(scenes[1]))
    scale, rotation = truth_to_world(frame)
    assert 1 / frame.scale_uncertainty <= scale <= frame.scale_uncertainty
    assert np.degrees(np.arccos(rotation[2, 2])) < 0.2
    assert frame.scale_source.startswith("prior: the support") and frame.scale_is_prior
    assert frame.scale_uncertainty == priors.SUPPORT_HEIGHT_BAND and frame.warnings == ()
    record = frame.record()
    assert record["up"] == [0.0, 0.0, 1.0] and np.asarray(record["capture_to_world"]).shape == (4, 4)
    assert record["scale_is_prior"] is True and record["warnings"] == []
    # every cue was heard and agrees: the table's planes (centres and surface), the level vote,
    # the ring of cameras, the straight edges of the table's legs and the objects
    cues = {c["key"]: c for c in record["evidence"]["cues"]}
    assert {"support_centres", "support_surface", "camera_vote", "orbit"} <= set(cues)
    assert all(c["used"] and c["angle_to_up_deg"] < 2.0 for c in cues.values())


def test_the_support_plane_is_the_table_top_in_the_world(scenes):
    """``SceneFrame.support``: the plane the frame found, in the world (+z, metres): the table top."""
    frame = resolve_frame(load_scene(scenes[1]), FrameConfig(scale=1 / UNITS_PER_METRE))
    support = frame.support
    assert support is not None and support.source in ("opaque Gaussian centres", "splat surface")
    assert estimate.angle_deg(support.normal, np.array([0.0, 0.0, 1.0])) < 0.3
    # the table top is 0.75 m over the truth's floor; the world keeps the capture's origin
    shift = split_sim3(frame.capture_to_world)[1] @ WORLD_TO_CAPTURE[:3, 3] / UNITS_PER_METRE
    assert support.height == pytest.approx(0.75 + shift[2], abs=0.01)
    record = frame.record()["support"]
    assert set(record) >= {"normal", "offset", "height", "point", "source", "inliers"} and record["height"] == pytest.approx(
        support.height)
    # rescaled (--known-size) the support stays on the same Gaussians: its height scales with the frame
    doubled = frame.rescaled(2 * frame.scale, "given", 1.0)
    assert doubled.support.height == pytest.approx(2 * support.height, rel=1e-9)


def test_known_size_rescales_to_the_given_length(scenes):
    frame = resolve_frame(load_scene(scenes[1]))
    box = np.random.default_rng(0).uniform([0, 0, 0], [0.3, 0.1, 0.05], (500, 3)) * frame.scale
    sized = with_known_size(frame, box, 4, 0.15)
    side = 0.3 * frame.scale  # the points' longest side, in metres at the frame's scale
    assert sized.scale == pytest.approx(frame.scale * 0.15 / side, rel=0.02)
    assert sized.scale_uncertainty > 1 and "--known-size 4=0.15" in sized.scale_source


def test_moving_into_the_world_changes_only_depth_units(scenes):
    scene = load_scene(scenes[1])
    frame = resolve_frame(scene, FrameConfig(scale=1 / UNITS_PER_METRE))
    world = frame.apply(scene)
    assert world.capture_to_world is not None
    for view in (0, 5):
        before = render(scene.require_gaussians().to_kernel(), scene.cameras[view])
        after = render(world.require_gaussians().to_kernel(), world.cameras[view])
        # float32 Gaussians moved by a Sim(3): a few splats of nearly equal depth may swap places
        difference = np.abs(np.asarray(after.rgb) - np.asarray(before.rgb))
        assert np.quantile(difference, 0.999) < 2e-3 and difference.max() < 0.02
        hit = np.asarray(before.alpha) > 0.5
        np.testing.assert_allclose(np.asarray(after.depth_normalized)[hit],
                                   np.asarray(before.depth_normalized)[hit] / UNITS_PER_METRE, rtol=1e-3, atol=1e-4)
    points = scene.require_gaussians().means[:10]
    np.testing.assert_allclose(world.to_world(points), world.require_gaussians().means[:10], atol=1e-5)
    with pytest.raises(ValueError, match="already"):
        scene_in_world(world, frame.capture_to_world)


def test_camera_votes_and_a_wall_without_support():
    """Cameras on an arc in front of a wall: their level vote is up; the wall (90° from it) is no
    support; no plane under them: the scale is a prior and says so."""
    rng = np.random.default_rng(1)
    up = rng.normal(size=3)
    up /= np.linalg.norm(up)
    from phirie_jax.frame.cues import Cue, decide_up
    from phirie_jax.geometry import rotation_to_z
    from phirie_jax.synthetic.scene import look_at
    from phirie_jax.types import Camera

    to_capture = rotation_to_z(up).T  # +z → up
    cameras = []
    for angle in np.linspace(-0.6, 0.6, 7):  # an arc in front of a wall, looking slightly down
        eye = np.array([np.sin(angle), -np.cos(angle), 0.3]) * 1.5
        w2c = look_at(eye, np.array([0.0, 0.0, 0.0]))
        moved = np.eye(4)
        moved[:3, :3] = w2c[:3, :3] @ to_capture.T
        moved[:3, 3] = w2c[:3, 3]
        cameras.append(Camera(f"{len(cameras)}.png", np.eye(3), moved, 100, 100))
    vote = estimate.cameras_up(cameras)
    assert estimate.angle_deg(vote, up) < 0.5  # level cameras: up ⟂ every x axis
    wall = estimate.Plane(to_capture @ np.array([0.0, -1.0, 0.0]), 0.0, 1000, 0.5, "centres")
    decision = decide_up([Cue("camera_vote", "cameras' level vote", vote, 5.0)], [wall], None, None, 0.01)
    assert estimate.angle_deg(decision.up, up) < 0.5 and decision.support is None
    assert decision.source.startswith("cameras' level vote")
    assert any("rests on cameras' level vote alone" in w for w in decision.warnings)
    scale, source, band, _ = priors.scale_prior(None, [wall], decision.up, tuple(cameras), None, 1.5 * 3)
    assert source.startswith("prior: the cameras 4.5 units from what they see") and band == priors.VIEW_DISTANCE_BAND
    assert scale == pytest.approx(priors.VIEW_DISTANCE_M / 4.5)


def test_known_size_observes_again_at_the_corrected_scale(scenes, tmp_path):
    """--known-size with the true longest side of object 1 recovers the capture's scale to within
    what one-sided observation loses, and the instances are written at that scale."""
    import json

    from phirie_jax.frame.resolve import longest_side
    from phirie_jax.io.mesh import load_trimesh
    from phirie_jax.pipeline import run_convert

    truth = json.loads((scenes[0] / "gt" / "objects.json").read_text())
    first = next(o for o in truth if o["id"] == 1)
    side = longest_side(load_trimesh(scenes[0] / first["mesh"]).vertices)
    manifest = run_convert(scenes[1], tmp_path / "out", masks="files", stages=("observe",),
                           frame=FrameConfig(known_size=f"1={side:.4f}"))
    scale = manifest["frame"]["scale"] * UNITS_PER_METRE          # 1 when exact
    assert 0.97 < scale < 1.12 and manifest["frame"]["scale_source"].startswith("given (--known-size 1=")
    assert set(manifest["timings"]) >= {"frame", "observe"} and "objects" not in manifest["timings"]
    record = next(i for i in manifest["instances"] if i["id"] == 1)
    observed = np.load(tmp_path / "out" / record["points"])["points"]
    assert longest_side(observed) < 0.5                           # metres, not capture units


def test_a_given_up_the_cues_refute_is_printed_and_recorded(scenes, tmp_path, capsys):
    """``--up`` wins, but a frame that is wrong is not silent: the cues' disagreement is a
    ``phirie: warning: frame:`` line on stderr and is kept in the manifest."""
    from phirie_jax.pipeline import run_convert

    manifest = run_convert(scenes[1], tmp_path / "out", stages=(), frame=FrameConfig(up="+x"))
    frame = manifest["frame"]
    assert frame["up_source"] == "given (--up +x)" and frame["warnings"]
    assert frame["warnings"][0].startswith("up cues disagree: ")
    err = capsys.readouterr().err
    assert f"phirie: warning: frame: {frame['warnings'][0]}" in err
    assert set(manifest["timings"]) >= {"frame"} and "observe" not in manifest["timings"]
