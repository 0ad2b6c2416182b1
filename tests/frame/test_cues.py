"""Cues that check each other, on small made-up captures: a plane cameras stand below is no
support, cues that disagree by more than 10° are a warning, an up resting on one cue is a
warning, the support lies under the point an orbit looks at, the composited surface is what
the cameras see, plumb edges give the vertical, and a prior says it is one."""

from __future__ import annotations

import numpy as np
import pytest

from phirie_jax.frame import estimate, lines, orbit, priors, surface
from phirie_jax.frame.cues import AGREE_DEG, Cue, choose_support, consensus, decide_up
from phirie_jax.geometry import rotation_to_z
from phirie_jax.synthetic.scene import look_at
from phirie_jax.types import Camera, GaussianSplatData

Z = np.array([0.0, 0.0, 1.0])


def tilted(degrees: float, azimuth: float = 0.0) -> np.ndarray:
    """(3,) +z turned by ``degrees`` towards the horizontal ``azimuth`` (radians)."""
    t = np.radians(degrees)
    return np.array([np.sin(t) * np.cos(azimuth), np.sin(t) * np.sin(azimuth), np.cos(t)])


def ring(count: int = 12, radius: float = 1.0, height: float = 0.6, target=(0.0, 0.0, 0.1), span=2 * np.pi,
         size: int = 64) -> list[Camera]:
    """Cameras on a (partial) ring around ``target``, level, looking at it."""
    K = np.array([[size, 0, size / 2], [0, size, size / 2], [0, 0, 1.0]])
    angles = np.linspace(0, span, count, endpoint=span < 2 * np.pi)
    return [Camera(f"{i:02d}.png", K, look_at(np.array([radius * np.cos(a), radius * np.sin(a), height]),
                                              np.asarray(target, float)), size, size) for i, a in enumerate(angles)]


def plane_points(normal, offset, rng, count=3000, extent=1.5) -> np.ndarray:
    """(count, 3) points on normal · x = offset, spread over a square of ``extent``."""
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    frame = rotation_to_z(normal).T
    local = np.column_stack([rng.uniform(-extent / 2, extent / 2, (count, 2)), np.zeros(count)])
    return local @ frame.T + offset * normal


def test_a_plane_cameras_stand_below_is_not_the_support():
    """A table under a ring of cameras, and a plane 20° off it that a quarter of the cameras
    stand below: the latter is turned towards most cameras, counts them, and is refused."""
    rng = np.random.default_rng(0)
    cameras = ring(16, height=0.5)
    slanted = tilted(20.0)
    points = np.concatenate([plane_points(Z, 0.0, rng, 4000), plane_points(slanted, 0.25, rng, 6000)])
    threshold = 0.005
    planes = estimate.oriented_planes(estimate.find_planes(points, threshold, rng), tuple(cameras), len(points),
                                      threshold, "centres", rng)
    wrong = max(planes, key=lambda p: p.inliers)   # the slanted plane holds the most points
    assert estimate.angle_deg(wrong.normal, slanted) < 1.0 and 0 < wrong.cameras_below < len(cameras) / 2
    support, why = choose_support(planes, estimate.cameras_up(cameras), None, None, threshold)
    assert estimate.angle_deg(support.normal, Z) < 0.5 and support.cameras_below == 0
    assert why[id(wrong)] == f"{wrong.cameras_below} camera(s) stand below it"
    decision = decide_up([Cue("camera_vote", "cameras' level vote", estimate.cameras_up(cameras), 5.0)], planes,
                         None, None, threshold)
    assert decision.support is support and estimate.angle_deg(decision.up, Z) < 0.5
    roles = {p["role"] for p in decision.evidence["planes"]}
    assert "support" in roles and any("stand below it" in r for r in roles)


def test_cues_that_disagree_by_more_than_10_degrees_are_a_warning():
    plane = Cue("support_centres", "support plane (opaque Gaussian centres)", tilted(0.5), 1.0)
    vote = Cue("camera_vote", "cameras' level vote", tilted(3.0, 2.0), 5.0)
    lines_cue = Cue("plumb_lines", "plumb lines", tilted(16.0, 1.0), 1.0)
    up, group = consensus([plane, vote, lines_cue])
    # the heaviest agreeing group: the plumb lines (16° off) are alone and lighter than plane + vote
    assert {c.key for c in group} == {"support_centres", "camera_vote"}
    assert estimate.angle_deg(up, Z) < 1.0
    decision = decide_up([vote, lines_cue], [], None, None, 0.01)
    assert decision.warnings[0] == "up cues disagree: cameras' level vote is 14.6° from plumb lines"
    angles = {c["key"]: c["angle_to_up_deg"] for c in decision.evidence["cues"]}
    assert decision.evidence["max_disagreement_deg"] > AGREE_DEG
    assert any(a > AGREE_DEG for a in angles.values())
    # agreeing cues: no warning, and the up is their weighted mean
    calm = decide_up([plane, vote], [], None, None, 0.01)
    assert calm.warnings == () and estimate.angle_deg(calm.up, plane.up) < estimate.angle_deg(calm.up, vote.up)


def test_an_up_resting_on_one_cue_or_a_given_up_the_cues_refute_is_a_warning():
    vote = Cue("camera_vote", "cameras' level vote", Z, 5.0)
    alone = decide_up([vote], [], None, None, 0.01)
    assert alone.warnings and "rests on cameras' level vote alone" in alone.warnings[0]
    given = decide_up([vote, Cue("plumb_lines", "plumb lines", tilted(1.0), 1.0)], [], None, None, 0.01,
                      given=(np.array([1.0, 0.0, 0.0]), "given (--up +x)"))
    assert np.allclose(given.up, [1, 0, 0]) and given.source == "given (--up +x)"
    assert given.warnings[0].startswith("up cues disagree: cameras' level vote is 90.0° from the given up")


def test_the_support_of_an_orbit_lies_under_the_point_it_looks_at():
    """A table top 0.75 over a larger floor: the floor holds more points, but the cameras look at
    the table top, which is the support; the floor gives the support-over-floor prior."""
    rng = np.random.default_rng(2)
    cameras = tuple(ring(16, radius=1.3, height=1.4, target=(0, 0, 0.8)))
    points = np.concatenate([plane_points(Z, 0.0, rng, 9000, 3.0), plane_points(Z, 0.75, rng, 5000, 1.0)])
    threshold = 0.01
    planes = estimate.oriented_planes(estimate.find_planes(points, threshold, rng), cameras, len(points), threshold,
                                      "centres", rng)
    around = orbit.orbit(cameras, estimate.cameras_up(cameras))
    assert around.is_orbit and around.surrounds and estimate.angle_deg(around.up, Z) < 1.0
    support, _ = choose_support(planes, Z, around, None, threshold)
    assert support.offset == pytest.approx(0.75, abs=0.01)
    scale, source, band, measured = priors.scale_prior(support, planes, Z, cameras, around, 1.0)
    assert source.startswith("prior: the support 0.75") and band == priors.SUPPORT_HEIGHT_BAND
    assert scale == pytest.approx(priors.SUPPORT_HEIGHT_M / 0.75, rel=0.02) and measured["kind"] == "support over floor"


def test_orbits_walks_and_arcs():
    level = ring(12)
    around = orbit.orbit(level, Z)
    assert around.is_orbit and around.surrounds and around.widest_gap_deg == pytest.approx(30.0, abs=0.1)
    arc = orbit.orbit(ring(9, span=np.radians(100)), Z)   # in front of a wall: no ring, no up of its own
    assert arc.is_orbit and not arc.surrounds and arc.up is None
    walk = [Camera(f"{i}.png", np.eye(3), look_at(np.array([x, 0.0, 1.5]), np.array([x, 2.0, 1.4])), 64, 64)
            for i, x in enumerate(np.linspace(0, 3, 8))]    # walking along a wall, looking at it
    assert orbit.orbit(walk, Z) is None or not orbit.orbit(walk, Z).is_orbit


def test_scale_priors_say_they_are_priors_and_fit_the_capture():
    cameras = tuple(ring(12, radius=0.3, height=0.2, target=(0, 0, 0.05)))
    around = orbit.orbit(cameras, Z)
    scale, source, band, _ = priors.scale_prior(None, [], Z, cameras, around, 0.35)
    assert source.startswith("prior: the cameras orbit a point") and "object-centric" in source
    assert band == priors.ORBIT_DISTANCE_BAND and scale == pytest.approx(priors.ORBIT_DISTANCE_M / around.distance)
    # a close-up orbit of an object 0.2–0.9 m away is inside the band; a room-scale walk is another prior
    assert priors.ORBIT_DISTANCE_M / band <= 0.2 and priors.ORBIT_DISTANCE_M * band >= 0.85
    table = estimate.Plane(Z, 0.0, 100, 0.5, "centres", 0, np.zeros((1, 3)))
    scale, source, band, _ = priors.scale_prior(table, [table], Z, cameras, None, 0.35)
    assert source.startswith("prior: the cameras 0.2 units over the support") and band == priors.CAMERA_HEIGHT_BAND


def test_the_frame_line_says_when_the_scale_is_a_prior(capsys):
    from phirie_jax.cli import _print_frame
    from phirie_jax.manifest import SCHEMA, Manifest

    record = {"scale": 0.088, "scale_source": "prior: the cameras orbit a point 4.5 units away",
              "scale_uncertainty": 2.2, "capture_up": [0.0, 0.0, 1.0], "up_source": "plumb lines",
              "support": {"source": "splat surface", "height": 0.74}}
    _print_frame(Manifest.from_json("out", {"schema": SCHEMA, "frame": record}))
    line = capsys.readouterr().out
    assert line.startswith("frame: 0.088 m per capture unit (prior: the cameras orbit") and "×/÷2.2" in line
    assert "support: splat surface at 0.74 m" in line
    _print_frame(Manifest.from_json("out", {"schema": SCHEMA, "frame": {**record, "support": None}}))
    assert "no support plane" in capsys.readouterr().out


def test_the_composited_surface_is_what_the_camera_sees():
    """Two sheets of Gaussians, 1 and 2 units in front of the camera: the front one is the surface
    where it is opaque; where it is faint (opacity 0.1, about two splats a pixel: 81 % of the
    light passes) the back sheet is; a sheet behind the camera never is."""
    camera = Camera("0.png", np.array([[64.0, 0, 32], [0, 64, 32], [0, 0, 1]]), np.eye(4), 64, 64)
    xy = np.stack(np.meshgrid(np.linspace(-0.45, 0.45, 40), np.linspace(-0.45, 0.45, 40)), -1).reshape(-1, 2)
    right = xy[xy[:, 0] > 0]
    front = np.column_stack([right, np.ones(len(right))])                      # the right half
    back = np.column_stack([2 * xy, np.full(len(xy), 2.0)])                     # everything, further away
    faint = np.column_stack([-right[:, 0], right[:, 1], np.ones(len(right))])   # the left half
    behind = np.column_stack([xy, -np.ones(len(xy))])
    means = np.concatenate([front, back, faint, behind])
    opacity = np.concatenate([np.full(len(front), 0.95), np.full(len(back), 0.95), np.full(len(faint), 0.1),
                              np.full(len(behind), 0.95)])
    sigma = np.full(len(means), 0.03)
    chosen = surface.composite_surface(means, opacity, sigma, camera, width=32)
    kinds = np.repeat(np.arange(4), [len(front), len(back), len(faint), len(behind)])[chosen]
    assert set(kinds.tolist()) == {0, 1}                  # never the faint sheet, never behind the camera
    assert abs((kinds == 0).sum() - (kinds == 1).sum()) < 0.1 * len(kinds)   # half the pixels each
    n = len(means)
    data = GaussianSplatData(means=means.astype(np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                             log_scales=np.log(np.full((n, 3), 0.03, np.float32)),
                             opacity_logits=np.log(opacity / (1 - opacity)).astype(np.float32),
                             sh=np.zeros((n, 1, 3), np.float32))
    points = surface.surface_points(data, (camera,), width=32)
    assert len(points) == len(chosen) and np.all(points[:, 2] > 0)


def vertical_segments(cameras, up, rng, count=30, clutter=60):
    """Per camera, (S, 4) segments: vertical 3D edges (direction ``up``) seen by it, and clutter."""
    out = []
    for cam in cameras:
        segments = []
        for _ in range(count):
            base = rng.uniform(-1.5, 1.5, 3)
            ends = np.array([base, base + rng.uniform(0.3, 0.8) * up])
            uv, depth = cam.project(ends)
            if (depth > 0.1).all():
                segments.append(uv.ravel())
        for _ in range(clutter):
            a = rng.uniform(0, cam.width, 2)
            angle = rng.uniform(0, np.pi)
            segments.append(np.r_[a, a + 40 * np.array([np.cos(angle), np.sin(angle)])])
        out.append(np.array(segments))
    return out


def test_plumb_lines_recover_the_vertical_among_clutter(monkeypatch):
    rng = np.random.default_rng(4)
    up = tilted(12.0, 0.7)
    to_capture = rotation_to_z(up).T
    cameras = []
    for cam in ring(10, radius=3.0, height=1.2, target=(0, 0, 0.5), size=640):
        pose = cam.world_to_camera.copy()
        pose[:3, :3] = pose[:3, :3] @ to_capture.T       # the world turned: +z becomes ``up``
        cameras.append(Camera(cam.name, cam.K, pose, cam.width, cam.height))
    segments = iter(vertical_segments(cameras, up, rng))
    monkeypatch.setattr(lines, "detect_segments", lambda camera: next(segments))
    found, why = lines.plumb_lines(tuple(cameras), estimate.cameras_up(cameras), rng)
    assert why == "" and estimate.angle_deg(found.up, up) < 0.2
    assert found.segments >= 100 and found.views == 10 and found.sigma_deg == lines.MIN_SIGMA_DEG
    # no plumb edges at all: the cue says why it is absent
    monkeypatch.setattr(lines, "detect_segments", lambda camera: vertical_segments([camera], up, rng, 0, 30)[0])
    none, why = lines.plumb_lines(tuple(cameras), estimate.cameras_up(cameras), rng)
    assert none is None and "straight edges" in why


def test_the_floor_is_found_under_a_rough_support_and_not_in_clutter():
    """RANSAC may spend its planes on the pieces of a rough table top; the floor is then looked
    for as the densest level where a floor can be (the support at 0.3–0.9 of the cameras' height
    over it). Points scattered at every height (a room's clutter) have no such level."""
    rng = np.random.default_rng(5)
    cameras = tuple(ring(12, radius=1.3, height=1.4, target=(0, 0, 0.8)))
    table = plane_points(Z, 0.75, rng, 4000, 1.0) + rng.normal(0, 0.01, (4000, 3))
    floor = plane_points(Z, 0.0, rng, 1500, 3.0)
    support = estimate.Plane(Z, 0.75, 4000, 0.5, "centres", 0, table)
    found = priors.find_floor(np.concatenate([table, floor]), support, Z, cameras, 0.01)
    assert found is not None and found.offset == pytest.approx(0.0, abs=0.01) and found.source == "floor"
    scale, source, band, _ = priors.scale_prior(support, [found], Z, cameras, None, 1.5)
    assert source.startswith("prior: the support 0.75") and scale == pytest.approx(priors.SUPPORT_HEIGHT_M / 0.75,
                                                                                   rel=0.02)
    clutter = rng.uniform([-1.5, -1.5, -0.5], [1.5, 1.5, 0.7], (1500, 3))
    assert priors.find_floor(np.concatenate([table, clutter]), support, Z, cameras, 0.01) is None
