"""The registration driver: buckets, one program per bucket across candidates, the batched
and the lazy retry agree, and a real scanned mesh (YCB, y-up) is placed through the retry."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from kernels.registration import SearchSpec
from phirie_jax.construct.objects import register as reg
from phirie_jax.construct.objects.candidates import Candidate
from phirie_jax.construct.objects.config import ObjectsConfig, RegistrationConfig
from phirie_jax.construct.objects.stage import register_candidate
from tests.conftest import shared_data
from tests.kernels.shapes import in_random_frame, l_shape, partial_view

SMALL = RegistrationConfig(search=SearchSpec(
    model_points=4096, sweep_model_points=256, sweep_obs_points=256, icp_model_points=1024, icp_obs_points=1024,
    score_obs_points=1024), hypothesis_batch=108)
F1_MIN = 0.9


def test_buckets_and_observation_layout():
    assert reg.obs_bucket(1, 256) == 256 and reg.obs_bucket(257, 256) == 512 and reg.obs_bucket(1024, 256) == 1024
    q = np.random.default_rng(0).random((300, 3))
    obs = reg.prepare_observation(q, 0.0, True, SMALL)
    assert obs.points.shape == (512, 3) and obs.mask[:300].all() and not obs.mask[300:].any()
    assert sorted(map(tuple, obs.points[:300].round(5))) == sorted(map(tuple, q.astype(np.float32).round(5)))


def test_the_scoring_floor_is_the_observations_cut_above_a_plane_support():
    """Q was cut 5 mm above a plane support (the cut recorded with its support): E leaves out the
    model below that height; without a cut (no plane under the instance) or with
    ``skip_cut_base`` off, nothing is left out."""
    q = np.random.default_rng(0).random((300, 3))
    assert reg.prepare_observation(q, 0.2, True, SMALL, cut=0.005).floor == pytest.approx(0.205)
    assert reg.prepare_observation(q, 0.2, True, SMALL).floor == -np.inf
    paper = dataclasses.replace(SMALL, skip_cut_base=False)
    assert reg.prepare_observation(q, 0.2, True, paper, cut=0.005).floor == -np.inf


def test_a_placed_base_below_the_floor_does_not_count_against_a_candidate():
    """An open box (a bowl's shape) placed on its support: the observation, cut 5 mm above the
    support, has nothing under its base; scored with the cut, E drops by the base's share."""
    from tests.kernels.shapes import box_surface

    rng = np.random.default_rng(4)
    pts, normals = box_surface((-0.06, -0.06, 0.0), (0.12, 0.12, 0.05), 6000, rng)
    q = pts[(normals[:, 2] <= 0.5) & (pts[:, 2] >= 0.005)][:800]
    vertices = np.array([[x, y, z] for x in (-0.06, 0.06) for y in (-0.06, 0.06) for z in (0.0, 0.05)])
    import trimesh

    mesh = trimesh.Trimesh(vertices, trimesh.convex.convex_hull(vertices).faces)
    model = reg.sample_model(mesh.vertices, mesh.faces, SMALL.points, 0)
    placement = np.eye(4)
    whole = reg.score_placement(model, reg.prepare_observation(q, 0.0, True, SMALL), placement, SMALL)
    cut = reg.score_placement(model, reg.prepare_observation(q, 0.0, True, SMALL, cut=0.005),
                              placement, SMALL)
    assert cut.model_to_obs < whole.model_to_obs - 0.002 and cut.energy < whole.energy
    assert cut.obs_to_model == pytest.approx(whole.obs_to_model, abs=2e-4)


def test_sample_model_lies_on_the_surface():
    import trimesh

    box = trimesh.creation.box(extents=[1.0, 2.0, 3.0])
    p = reg.sample_model(box.vertices, box.faces, 2000, 0)
    assert p.shape == (2000, 3) and p.dtype == np.float32
    on_face = np.isclose(np.abs(p), [0.5, 1.0, 1.5], atol=1e-5).any(axis=1)
    assert on_face.all()
    # area-weighted: the two 2×3 faces (x = ±0.5) hold 12/22 of the area
    assert np.mean(np.isclose(np.abs(p[:, 0]), 0.5, atol=1e-5)) == pytest.approx(12 / 22, abs=0.04)


def test_no_retrace_across_candidates_of_the_same_bucket():
    rng = np.random.default_rng(1)
    points, normals = l_shape(6000, rng)
    q = partial_view(points, normals, 700, rng)
    obs_a = reg.prepare_observation(q, 0.0, True, SMALL)
    obs_b = reg.prepare_observation(q[:550], 0.0, True, SMALL)
    assert obs_a.points.shape == obs_b.points.shape
    model_a = reg.sample_model(*l_mesh(1.0), SMALL.points, 0)
    model_b = reg.sample_model(*l_mesh(1.7), SMALL.points, 1)
    reg.search(model_a, obs_a, SMALL, reg.ALL_AXES)
    before = reg.TRACE_COUNTS["register"]
    assert before >= 1  # the counter counts (this program was traced here or by an earlier test)
    reg.search(model_b, obs_b, SMALL, reg.ALL_AXES)
    reg.search(model_a, obs_b, SMALL, reg.ALL_AXES)
    assert reg.TRACE_COUNTS["register"] == before


def l_mesh(scale):
    import trimesh

    a = trimesh.creation.box(extents=[0.12, 0.06, 0.04])
    a.apply_translation([0.06, 0.03, 0.02])
    b = trimesh.creation.box(extents=[0.04, 0.06, 0.10])
    b.apply_translation([0.02, 0.03, 0.09])
    m = trimesh.util.concatenate([a, b])
    return m.vertices * scale, m.faces


def _l_candidate_in_a_y_up_frame():
    import trimesh

    rng = np.random.default_rng(2)
    v, f = l_mesh(1.0)
    world = trimesh.Trimesh(v - [0.06, 0.03, 0.0], f)
    pts, face = trimesh.sample.sample_surface(world, 6000, seed=3)
    q = partial_view(pts, world.face_normals[face], 800, rng)
    file_frame, truth = in_random_frame(np.asarray(world.vertices), 3, rng)   # up is the file's +y
    cand = Candidate("external:l", "external", 0, file_frame.astype(np.float64), np.asarray(world.faces), None)
    return cand, reg.prepare_observation(q, 0.0, True, SMALL), truth


def test_batched_retry_takes_the_right_axis_in_one_call():
    cand, obs, truth = _l_candidate_in_a_y_up_frame()
    batched = register_candidate(cand, obs, ObjectsConfig(registration=SMALL))
    assert batched["kernel_calls"] == 1 and batched["retry"]["used"] and batched["scores"]["axis"] == "+y"
    assert batched["retry"]["own_up_failed"] and batched["retry"]["axes"][0]["axis"] == "+z"
    scale = np.cbrt(np.linalg.det(truth[:3, :3]))
    np.testing.assert_allclose(batched["gravity_matrix"][:3, :3], truth[:3, :3], atol=0.05 * scale)


def test_the_registration_bound_scales_with_the_observation_unless_discovery_found_it():
    cand, obs, _ = _l_candidate_in_a_y_up_frame()
    config = ObjectsConfig(registration=SMALL, max_relative_residual=0.5)   # half of Q's size: loose
    pointed = register_candidate(cand, obs, config)["checks"]["registration"]
    found = register_candidate(cand, obs, config, size_bound=False)["checks"]["registration"]
    assert pointed["observed_size"] == pytest.approx(reg.observed_size(obs.points[obs.mask]), rel=1e-5)
    assert pointed["threshold"] == pytest.approx(0.5 * pointed["observed_size"])
    assert pointed["threshold"] > config.max_residual
    assert found["threshold"] == config.max_residual and found["observed_size"] == 0.0


@pytest.mark.slow
def test_lazy_retry_and_no_retry_agree_with_the_batched_call():
    cand, obs, truth = _l_candidate_in_a_y_up_frame()
    batched = register_candidate(cand, obs, ObjectsConfig(registration=SMALL))
    lazy_cfg = ObjectsConfig(registration=dataclasses.replace(SMALL, batched_retry=False))
    lazy = register_candidate(cand, obs, lazy_cfg)
    assert lazy["kernel_calls"] == 2 and lazy["retry"]["used"] and lazy["scores"]["axis"] == "+y"
    np.testing.assert_allclose(batched["gravity_matrix"], lazy["gravity_matrix"], atol=1e-3)
    no_retry = register_candidate(cand, obs, ObjectsConfig(registration=SMALL, retry=False))
    assert no_retry["scores"]["axis"] == "+z" and not no_retry["retry"]["used"] and no_retry["kernel_calls"] == 1
    assert no_retry["scores"]["energy"] > batched["scores"]["energy"]


def test_a_scanned_y_up_mesh_is_placed_through_the_retry():
    import jax.numpy as jnp
    import trimesh

    from kernels.metrics import f1_score

    path = shared_data("ycb", "006_mustard_bottle_textured.gltf")
    mesh = trimesh.load(path, force="mesh")                       # y-up, metres, not watertight
    to_z = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])     # y-up → z-up
    world = trimesh.Trimesh(mesh.vertices @ to_z.T, mesh.faces, process=False)
    world.apply_translation(-np.array([*world.bounds.mean(0)[:2], world.bounds[0, 2]]))
    rng = np.random.default_rng(4)
    pts, face = trimesh.sample.sample_surface(world, 20000, seed=5)
    q = partial_view(pts, world.face_normals[face], 1500, rng)
    cand = Candidate("external:mustard", "external", 0, np.asarray(mesh.vertices), np.asarray(mesh.faces), None)
    out = register_candidate(cand, reg.prepare_observation(q, 0.0, True, SMALL),
                             ObjectsConfig(registration=SMALL))
    assert out["retry"]["used"] and out["scores"]["axis"] in ("+y", "-y")
    m = out["gravity_matrix"]
    placed = reg.sample_model(np.asarray(mesh.vertices) @ m[:3, :3].T + m[:3, 3], mesh.faces, 5000, 0)
    ref = reg.sample_model(world.vertices, world.faces, 5000, 1)
    f1, _, _ = f1_score(jnp.asarray(placed), jnp.ones(5000, bool), jnp.asarray(ref), jnp.ones(5000, bool), 0.02)
    assert float(f1) >= F1_MIN


def test_the_search_is_the_kernels_spec_with_the_per_call_fields_set_by_the_stage():
    spec = reg.search_spec(SMALL, (0,), snap=True)
    assert spec == dataclasses.replace(SMALL.search, axes=(0,), hypothesis_batch=108, snap_to_support=True)
    for field, value in (("axes", (0,)), ("snap_to_support", True), ("hypothesis_batch", 7)):
        with pytest.raises(ValueError, match=f"registration.search.{field}"):
            RegistrationConfig(search=SearchSpec(**{field: value}))


def test_the_cut_travels_with_the_instances_support():
    """The observation records its cut with the support it made it above; the objects stage reads it
    back from there (an older record without one: no cut, E scores every point)."""
    from phirie_jax.observe.support import Support

    cut = Support(0.2, "surface", 40, np.array([0.0, 0.0, 1.0]), 0.005)
    back = Support.from_record(cut.as_record())
    assert back.clearance == 0.005 and back.is_plane
    older = {k: v for k, v in cut.as_record().items() if k != "clearance"}
    assert Support.from_record(older).clearance is None
    q = np.random.default_rng(1).random((300, 3))
    assert reg.prepare_observation(q, back.height, True, SMALL, cut=back.clearance).floor == pytest.approx(0.205)
