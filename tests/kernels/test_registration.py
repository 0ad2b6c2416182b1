"""Registration kernels: E against a NumPy reference, Kabsch/ICP/scale refinement properties,
recovery of a known Sim(3) from a partial view for every up axis, and the retry of a wrong
up axis within the same batched call. (One program per shape bucket is tested where the
buckets are made: ``tests/construct/objects/test_register.py``.)"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kernels.chamfer import clipped_chamfer
from kernels.registration import (
    AXIS_NAMES,
    AXIS_ROTATIONS,
    UP_AXES,
    SearchSpec,
    _kabsch,
    axis_rotation,
    hypothesis_energy,
    icp,
    refine_scale,
    register,
    robust_extents,
    scale_init,
    yaw_matrix,
)
from phirie_jax.geometry import rotation_to_z
from tests.kernels.shapes import box_surface, in_random_frame, l_shape, padded, partial_view

TAU = 0.03
MAX_CORR = 0.06
ROT_TOL_DEG = 3.0     # rotation recovered to within this
SCALE_TOL = 0.02      # relative
TRANS_TOL = 0.006     # metres
ENERGY_TOL = 1e-6     # metres: registration's E against kernels.chamfer's on the same placement (float32
                      # rounding of the placement computed inside and outside the jitted program)
# a smaller program than the paper's (fast CPU tests); same search: 6 axes × 36 yaws × 3 scales
TEST_SPEC = SearchSpec(model_points=4096, sweep_model_points=256, sweep_obs_points=256, icp_model_points=1024,
                       icp_obs_points=1024, score_obs_points=1024, hypothesis_batch=108, snap_to_support=True)
_register = jax.jit(register, static_argnames=("spec",))


def run(model, q, bucket=1024, spec=TEST_SPEC):
    obs, mask = padded(q, bucket)
    return jax.device_get(_register(jnp.asarray(model), jnp.asarray(obs), jnp.asarray(mask), jnp.float32(0.0),
                                    jnp.bool_(True), jnp.float32(TAU), jnp.float32(MAX_CORR), spec=spec))


def rotation_angle_deg(a, b):
    cos = (np.trace(a.T @ b) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1))))


def sim3_error(result, row, truth):
    scale_t = np.cbrt(np.linalg.det(truth[:3, :3]))
    return (rotation_angle_deg(np.asarray(result.rotation[row]), truth[:3, :3] / scale_t),
            abs(float(result.scale[row]) / scale_t - 1), float(np.abs(result.translation[row] - truth[:3, 3]).max()))


@pytest.fixture(scope="module")
def shape():
    rng = np.random.default_rng(0)
    points, normals = l_shape(8000, rng)
    q = partial_view(points, normals, 900, rng)
    return points, q[rng.permutation(len(q))]


def test_axis_rotations_are_proper_and_take_the_axis_up():
    for axis in UP_AXES:
        r = axis_rotation(axis)
        np.testing.assert_allclose(r @ axis, [0, 0, 1], atol=1e-12)
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0)


def test_axis_rotation_table_is_the_hosts_rotation_to_z():
    assert AXIS_ROTATIONS.shape == (len(UP_AXES), 3, 3) and len(AXIS_NAMES) == len(UP_AXES)
    for k, axis in enumerate(UP_AXES):
        np.testing.assert_array_equal(AXIS_ROTATIONS[k], rotation_to_z(axis))
        np.testing.assert_array_equal(axis_rotation(axis), AXIS_ROTATIONS[k])


def test_hypothesis_energy_is_chamfers_clipped_chamfer_of_the_placed_model():
    rng = np.random.default_rng(5)
    model = rng.normal(0, 1, (300, 3)).astype(np.float32)
    obs = (rng.normal(0, 0.05, (200, 3)) + [0.2, 0.1, 0.5]).astype(np.float32)
    obs_p, mask = padded(obs, 256)
    rot = jnp.asarray(np.asarray(yaw_matrix(jnp.float32(0.3))) @ AXIS_ROTATIONS[1], jnp.float32)
    s, t = jnp.float32(0.05), jnp.float32([0.2, 0.1, 0.5])
    e, mq, qm, _ = hypothesis_energy(jnp.asarray(model), jnp.asarray(obs_p), jnp.asarray(mask), rot, s, t, TAU, 64)
    placed = s * jnp.asarray(model) @ rot.T + t
    ref = clipped_chamfer(placed, jnp.ones(len(model), bool), jnp.asarray(obs_p), jnp.asarray(mask), TAU, 64)
    np.testing.assert_allclose([float(e), float(mq), float(qm)], [float(x) for x in ref], atol=ENERGY_TOL)


def test_registered_energy_is_chamfers_E_of_the_returned_placement(shape):
    points, q = shape
    spec = SearchSpec(axes=(0, 3), num_yaws=4, scale_multipliers=(1.0,), model_points=1024, sweep_model_points=128,
                      sweep_obs_points=128, icp_model_points=256, icp_obs_points=256, score_obs_points=512,
                      icp_iterations=2, scale_iterations=2, refine_other_axes=1, hypothesis_batch=8)
    model = points[np.random.default_rng(3).permutation(len(points))[:1024]].astype(np.float32)
    result = run(model, q, bucket=1024, spec=spec)
    obs, mask = padded(q, 1024)
    obs, mask = obs[:spec.score_obs_points], mask[:spec.score_obs_points]
    for row in range(len(result.energy)):
        placed = float(result.scale[row]) * model @ np.asarray(result.rotation[row]).T + np.asarray(result.translation[row])
        e, ab, ba = clipped_chamfer(jnp.asarray(placed), jnp.ones(len(model), bool), jnp.asarray(obs),
                                    jnp.asarray(mask), TAU, spec.chunk)
        np.testing.assert_allclose([float(result.energy[row]), float(result.model_to_obs[row]),
                                    float(result.obs_to_model[row])], [float(e), float(ab), float(ba)],
                                   atol=ENERGY_TOL)


def test_energy_matches_numpy_reference():
    rng = np.random.default_rng(1)
    model = rng.normal(0, 1, (300, 3)).astype(np.float32)
    obs = (rng.normal(0, 0.05, (200, 3)) + [0.2, 0.1, 0.5]).astype(np.float32)
    mask = np.arange(256) < 200
    obs_p, _ = padded(obs, 256)
    rot = np.asarray(yaw_matrix(jnp.float32(0.7))) @ axis_rotation(UP_AXES[3])
    s, t = 0.05, np.float32([0.2, 0.1, 0.5])
    e, mq, qm, sup = hypothesis_energy(jnp.asarray(model), jnp.asarray(obs_p), jnp.asarray(mask),
                                       jnp.asarray(rot, jnp.float32), jnp.float32(s), jnp.asarray(t), TAU, 64)
    placed = s * model.astype(np.float64) @ rot.T + t
    d_mq = np.array([np.min(np.linalg.norm(obs - p, axis=1)) for p in placed])
    d_qm = np.array([np.min(np.linalg.norm(placed - q, axis=1)) for q in obs])
    ref_mq, ref_qm = np.minimum(d_mq, TAU).mean(), np.minimum(d_qm, TAU).mean()
    np.testing.assert_allclose([float(mq), float(qm), float(e)], [ref_mq, ref_qm, ref_mq + ref_qm], atol=2e-6)
    assert float(sup) == pytest.approx(np.mean(d_qm <= TAU), abs=1e-6)


def test_scale_init_recovers_a_known_scale_whatever_the_yaw():
    rng = np.random.default_rng(2)
    points, _ = l_shape(4000, rng)
    obs = 3.7 * points @ np.asarray(yaw_matrix(jnp.float32(1.1))).T
    ext = robust_extents(jnp.asarray(obs, jnp.float32), jnp.ones(len(obs), bool))
    assert float(scale_init(jnp.asarray(points, jnp.float32), ext)) == pytest.approx(3.7, rel=1e-3)


@pytest.mark.parametrize("yaw_only", [False, True])
def test_kabsch_recovers_an_exact_rigid_motion(yaw_only):
    rng = np.random.default_rng(3)
    src = rng.normal(0, 1, (50, 3))
    if yaw_only:
        rot = np.asarray(yaw_matrix(jnp.float32(2.0)), np.float64)
    else:
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        rot = q * np.sign(np.linalg.det(q))
    t = np.array([0.3, -1.0, 2.0])
    dst = src @ rot.T + t
    r_est, t_est = _kabsch(jnp.asarray(src, jnp.float32), jnp.asarray(dst, jnp.float32), jnp.ones(50), yaw_only)
    np.testing.assert_allclose(np.asarray(r_est), rot, atol=1e-4)
    np.testing.assert_allclose(np.asarray(t_est), t, atol=1e-4)


def test_icp_and_scale_refinement_converge_from_a_nearby_start(shape):
    points, q = shape
    model = jnp.asarray(points[np.random.default_rng(4).permutation(len(points))[:2000]], jnp.float32)
    obs, mask = (jnp.asarray(x) for x in padded(q, 1024))
    start = np.asarray(yaw_matrix(jnp.float32(np.radians(8.0))))
    rot, t = icp(model, obs, mask, jnp.asarray(start, jnp.float32), jnp.float32(1.0), jnp.float32([0.01, -0.008, 0.0]),
                 jnp.float32(MAX_CORR), 30, False, 256)
    assert rotation_angle_deg(np.asarray(rot), np.eye(3)) < 1.0
    np.testing.assert_allclose(np.asarray(t), 0.0, atol=0.003)
    s, t2 = refine_scale(model, obs, mask, jnp.eye(3), jnp.float32(1.1), jnp.zeros(3), jnp.float32(MAX_CORR), 15, 256)
    assert float(s) == pytest.approx(1.0, abs=0.01)


@pytest.mark.parametrize("axis", range(6))
def test_known_sim3_is_recovered_from_a_partial_view_for_every_up_axis(shape, axis):
    points, q = shape
    rng = np.random.default_rng(10 + axis)
    model, truth = in_random_frame(points, axis, rng)
    result = run(model[rng.permutation(len(model))][: TEST_SPEC.model_points], q)
    best = int(np.argmin(result.energy))
    assert AXIS_NAMES[int(result.axis[best])] == AXIS_NAMES[axis]
    rot_err, scale_err, trans_err = sim3_error(result, best, truth)
    assert rot_err < ROT_TOL_DEG and scale_err < SCALE_TOL and trans_err < TRANS_TOL
    assert float(result.support[best]) > 0.95 and float(result.energy[best]) < 0.012


def test_retry_fixes_a_wrong_up_axis_in_the_same_call(shape):
    points, q = shape
    rng = np.random.default_rng(20)
    model, truth = in_random_frame(points, 3, rng)  # the file's up is +y, not its own +z
    every = run(model[rng.permutation(len(model))][: TEST_SPEC.model_points], q)
    own = 0                                          # rows are axis-major: row 0 is the own up (+z)
    assert AXIS_NAMES[int(every.axis[own])] == "+z"
    best = int(np.argmin(every.energy))
    assert AXIS_NAMES[int(every.axis[best])] == "+y"
    assert float(every.energy[own]) > 2 * float(every.energy[best])  # the own-up answer is visibly worse
    rot_err, scale_err, trans_err = sim3_error(every, best, truth)
    assert rot_err < ROT_TOL_DEG and scale_err < SCALE_TOL and trans_err < TRANS_TOL
    scale_t = np.cbrt(np.linalg.det(truth[:3, :3]))
    assert rotation_angle_deg(np.asarray(every.rotation[own]), truth[:3, :3] / scale_t) > 30


FLOOR = 0.005  # the observation's support clearance: Q has no point lower than this


def _open_box(n, rng, size=(0.12, 0.12, 0.05)):
    """A bowl-like open box on z = 0 (floor and four walls, no lid): points (n, 3)."""
    pts, normals = box_surface((-size[0] / 2, -size[1] / 2, 0.0), size, 2 * n, rng)
    return pts[normals[:, 2] <= 0.5][:n]   # drop the lid


def _reference(placed, obs, floor):
    """NumPy E over the placed model points at or above ``floor`` (all of them below half)."""
    keep = placed[:, 2] >= floor
    if keep.mean() < 0.5:
        keep[:] = True
    p = placed[keep]
    d_mq = np.array([np.min(np.linalg.norm(obs - x, axis=1)) for x in p])
    d_qm = np.array([np.min(np.linalg.norm(p - q, axis=1)) for q in obs])
    return np.minimum(d_mq, TAU).mean(), np.minimum(d_qm, TAU).mean()


def test_energy_leaves_out_the_model_below_the_floor_like_a_numpy_reference():
    """The candidate's base stands on the support, where the observation has no point: with the
    floor, its points take no part in E, which falls to the reference over the rest."""
    rng = np.random.default_rng(7)
    model = _open_box(1200, rng).astype(np.float32)
    obs = _open_box(1500, rng)
    obs = obs[obs[:, 2] >= FLOOR][:400].astype(np.float32)   # the observation is cut like Q
    obs_p, mask = padded(obs, 512)
    args = (jnp.asarray(model), jnp.asarray(obs_p), jnp.asarray(mask), jnp.eye(3), jnp.float32(1.0),
            jnp.zeros(3), TAU, 64)
    e_all, mq_all, _, _ = hypothesis_energy(*args)
    e_cut, mq_cut, qm_cut, _ = hypothesis_energy(*args, jnp.float32(FLOOR))
    ref_mq, ref_qm = _reference(model.astype(np.float64), obs.astype(np.float64), FLOOR)
    np.testing.assert_allclose([float(mq_cut), float(qm_cut), float(e_cut)], [ref_mq, ref_qm, ref_mq + ref_qm],
                               atol=2e-6)
    assert float(mq_cut) < 0.5 * float(mq_all) and float(e_cut) < float(e_all)
    # −inf (no cut) is the paper's E
    e_inf = hypothesis_energy(*args, jnp.float32(-np.inf))[0]
    assert float(e_inf) == pytest.approx(float(e_all), abs=ENERGY_TOL)


def test_a_model_mostly_below_the_floor_is_scored_whole():
    """A 4 mm slab (an optimiser's bump) lies under a 5 mm floor: scoring what is left would
    judge it on nothing, so every point is scored."""
    rng = np.random.default_rng(8)
    slab, _ = box_surface((-0.05, -0.05, 0.0), (0.1, 0.1, 0.004), 800, rng)
    obs, mask = padded((slab[:300] + [0.0, 0.0, 0.01]).astype(np.float32), 512)
    args = (jnp.asarray(slab, jnp.float32), jnp.asarray(obs), jnp.asarray(mask), jnp.eye(3), jnp.float32(1.0),
            jnp.zeros(3), TAU, 64)
    whole = [float(x) for x in hypothesis_energy(*args)[:3]]
    cut = [float(x) for x in hypothesis_energy(*args, jnp.float32(FLOOR))[:3]]
    np.testing.assert_allclose(cut, whole, atol=ENERGY_TOL)


def test_registered_energy_with_a_floor_is_the_cut_E_of_the_returned_placement(shape):
    points, q = shape
    spec = SearchSpec(axes=(0,), num_yaws=4, scale_multipliers=(1.0,), model_points=1024, sweep_model_points=128,
                      sweep_obs_points=128, icp_model_points=256, icp_obs_points=256, score_obs_points=512,
                      icp_iterations=2, scale_iterations=2, refine_other_axes=0, hypothesis_batch=4)
    model = points[np.random.default_rng(3).permutation(len(points))[:1024]].astype(np.float32)
    obs, mask = padded(q, 1024)
    result = jax.device_get(_register(jnp.asarray(model), jnp.asarray(obs), jnp.asarray(mask), jnp.float32(0.0),
                                      jnp.bool_(True), jnp.float32(TAU), jnp.float32(MAX_CORR), spec=spec,
                                      floor=jnp.float32(FLOOR)))
    obs, mask = obs[:spec.score_obs_points], mask[:spec.score_obs_points]
    for row in range(len(result.energy)):
        placed = float(result.scale[row]) * model @ np.asarray(result.rotation[row]).T + np.asarray(result.translation[row])
        keep = placed[:, 2] >= FLOOR
        assert 0.5 < keep.mean() < 1.0   # the cut is in play
        e, ab, ba = clipped_chamfer(jnp.asarray(placed), jnp.asarray(keep), jnp.asarray(obs), jnp.asarray(mask),
                                    TAU, spec.chunk)
        np.testing.assert_allclose([float(result.energy[row]), float(result.model_to_obs[row]),
                                    float(result.obs_to_model[row])], [float(e), float(ab), float(ba)],
                                   atol=ENERGY_TOL)
