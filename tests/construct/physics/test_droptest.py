"""The drop-test protocol with the MuJoCo C reference: spawn, known verdicts, ghost parts, errors."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from phirie_jax.construct.physics.collision import convex_part, hull_part
from phirie_jax.construct.physics.config import DropTestConfig, PhysicsConfig
from phirie_jax.construct.physics.droptest import (
    DropResult,
    body_from_parts,
    build_model,
    drop_test,
    drop_test_meshes,
    settling_check,
    spawn_qpos,
    verdict,
)
from phirie_jax.construct.physics.ground import PLANE_SIZE
from phirie_jax.geometry import split_sim3
from tests.fixtures import droptest_cases as cases

TOUCH_TOL = 1e-12     # m, lowest point on the plane at spawn
GHOST_TOL = 1e-9      # m, ghost parts change no state
FLOAT32_MESH = 1e-7   # m, MuJoCo stores mesh vertices in float32: contact depth at spawn within this


def pose(rotvec=(0.0, 0.0, 0.0), translation=(0.3, -0.2, 0.75), scale=1.0):
    out = np.eye(4)
    out[:3, :3] = scale * Rotation.from_rotvec(rotvec).as_matrix()
    out[:3, 3] = translation
    return out


def test_spawn_puts_the_lowest_point_on_the_plane_without_interpenetration():
    rng = np.random.default_rng(0)
    part = convex_part(rng.normal(size=(50, 3)) * [0.05, 0.03, 0.08], 64)
    for _ in range(5):
        body = body_from_parts((part,), pose(Rotation.random(random_state=rng).as_rotvec()))
        q = spawn_qpos(body)
        lowest = min((p.vertices @ body.rotation.T)[:, 2].min() for p in body.parts) + q[2]
        assert abs(lowest) < TOUCH_TOL
        model = build_model(body, 1, DropTestConfig())
        data = mujoco.MjData(model)
        data.qpos[:] = q
        mujoco.mj_forward(model, data)
        assert all(data.contact[i].dist >= -FLOAT32_MESH for i in range(data.ncon))   # nothing inside the plane


def test_scene_up_and_pose_scale_are_honoured():
    box = hull_part(trimesh.creation.box([0.1, 0.06, 0.04]).vertices)
    up = Rotation.from_rotvec([0.4, 0.2, 0.0]).as_matrix()      # a scene whose up is tilted
    placed = pose(scale=2.0)
    placed[:3, :3] = up @ placed[:3, :3]
    body = body_from_parts((box,), placed, up=up[:, 2])
    np.testing.assert_allclose(body.rotation, np.eye(3), atol=1e-12)    # upright in the gravity frame
    np.testing.assert_allclose(np.ptp(body.parts[0].vertices, axis=0), [0.2, 0.12, 0.08], atol=1e-12)
    with pytest.raises(ValueError, match="similarity|uniform"):
        split_sim3(np.diag([1.0, 2.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="determinant"):
        split_sim3(np.diag([1.0, 1.0, -1.0, 1.0]))


def test_a_box_on_its_face_is_stable_and_a_cone_on_its_tip_is_not():
    box = trimesh.creation.box([0.1, 0.06, 0.04])
    cone = trimesh.creation.cone(0.04, 0.15, sections=24)
    results = drop_test_meshes([(box.vertices, box.faces), (cone.vertices, cone.faces)],
                               [pose([0.0, 0.0, 0.7]), pose([np.pi + 0.05, 0.0, 0.0])], backend="mujoco")
    stable, tipped = results
    assert stable.stable and stable.drift_m < 1e-3 and stable.final_height_m == pytest.approx(0.02, abs=1e-3)
    assert not tipped.stable and tipped.drift_m > 0.05 and tipped.tilt_deg > 45
    assert stable.error is None and tipped.error is None


def test_the_reference_agrees_with_statics_on_the_case_set():
    agreement = cases.case_set(20, seed=5)
    bodies = [body_from_parts((hull_part(c.vertices),), c.pose) for c in agreement]
    results = drop_test(bodies, backend="mujoco")
    wrong = [c.name for c, r in zip(agreement, results) if r.stable != c.expected_stable]
    assert not wrong


def test_solver_settings_reach_the_model_and_the_verdicts_do_not_depend_on_them():
    agreement = cases.case_set(10, seed=6)
    bodies = [body_from_parts((hull_part(c.vertices),), c.pose) for c in agreement]
    verdicts = {}
    for solver, jacobian in (("newton", "dense"), ("cg", "sparse")):
        config = DropTestConfig(solver=solver, jacobian=jacobian, solver_iterations=30)
        model = build_model(bodies[0], 1, config)
        assert model.opt.solver == (mujoco.mjtSolver.mjSOL_CG if solver == "cg" else mujoco.mjtSolver.mjSOL_NEWTON)
        assert model.opt.jacobian == (mujoco.mjtJacobian.mjJAC_SPARSE if jacobian == "sparse"
                                      else mujoco.mjtJacobian.mjJAC_DENSE)
        assert model.opt.iterations == 30
        verdicts[solver] = [r.stable for r in drop_test(bodies, config, backend="mujoco")]
    assert verdicts["newton"] == verdicts["cg"] == [c.expected_stable for c in agreement]


@pytest.mark.parametrize("field, line", [({"solver": "pgs"}, "DropTestConfig.solver pgs: expected one of newton, cg"),
                                         ({"jacobian": "auto"}, "DropTestConfig.jacobian auto: expected one of dense, "
                                                                "sparse")])
def test_unknown_solver_settings_are_refused(field, line):
    with pytest.raises(ValueError, match=f"^{line}$"):
        DropTestConfig(**field)


def test_ghost_parts_change_nothing():
    cone = hull_part(trimesh.creation.cone(0.04, 0.15, sections=24).vertices)
    body = body_from_parts((cone,), pose([np.pi + 0.1, 0.0, 0.0]))
    config = DropTestConfig(settle_time=0.5, free_time=0.5)
    finals = []
    for bucket in (1, 4):
        model = build_model(body, bucket, config)
        assert model.ngeom == 1 + bucket
        data = mujoco.MjData(model)
        data.qpos[:] = spawn_qpos(body)
        mujoco.mj_step(model, data, nstep=config.settle_steps + config.free_steps)
        finals.append(data.qpos.copy())
    np.testing.assert_allclose(finals[1], finals[0], atol=GHOST_TOL)


def test_the_drop_model_and_the_warp_bank_share_plane_and_options():
    """Both builders take the plane and the solver options from construct/physics/ground.py (the bank
    model needs only MuJoCo to build)."""
    from phirie_jax.construct.physics import warp_batch

    config = DropTestConfig(solver="cg", jacobian="dense", solver_iterations=7)
    cube = hull_part(trimesh.creation.box([0.1, 0.1, 0.1]).vertices)
    model = build_model(body_from_parts((cube,), pose()), 1, config)
    bank, _ = warp_batch.bank_model([model], config)
    for m in (model, bank):
        plane = m.geom("plane")
        assert m.geom_type[plane.id] == mujoco.mjtGeom.mjGEOM_PLANE
        np.testing.assert_array_equal(m.geom_size[plane.id], PLANE_SIZE)
        assert (m.opt.timestep, m.opt.iterations, m.opt.solver, m.opt.jacobian) == (
            config.timestep, 7, mujoco.mjtSolver.mjSOL_CG, mujoco.mjtJacobian.mjJAC_DENSE)


def test_one_bad_candidate_does_not_stop_the_others():
    box = trimesh.creation.box([0.1, 0.1, 0.1])
    meshes = [(box.vertices, box.faces), (np.zeros((0, 3)), np.zeros((0, 3), int)),
              (box.vertices * [1, 1, 0], box.faces), (box.vertices, box.faces)]
    poses = [pose(), pose(), pose(), np.diag([1.0, 1.0, 2.0, 1.0])]
    results = drop_test_meshes(meshes, poses, config=PhysicsConfig(drop_test=DropTestConfig(backend="mujoco")))
    assert results[0].stable and results[0].error is None
    assert all(r == DropResult.not_run("mujoco", r.error) and r.error for r in results[1:])
    assert all(v is None for v in (results[1].drift_m, results[1].final_height_m, results[1].settle_drift_m,
                                   results[1].tilt_deg))
    assert "hull" in results[1].error and "flat" in results[2].error and "pose" in results[3].error


@pytest.mark.parametrize("broken", [np.nan, 0.0])
def test_a_diverged_state_is_unstable_with_a_reason(broken):
    body = body_from_parts((hull_part(trimesh.creation.box([0.1, 0.1, 0.1]).vertices),), pose())
    model, qpos0 = build_model(body, 1, DropTestConfig()), spawn_qpos(body)
    final = qpos0.copy()
    final[3:7] = broken          # NaN state, or a zero quaternion left by a diverged solver
    result = verdict(model, qpos0, qpos0, final, DropTestConfig(), "mjx")
    assert result.stable is False and "diverged" in result.error and result.drift_m is None


def test_settling_check_rows():
    box = trimesh.creation.box([0.1, 0.1, 0.1])
    ok, bad = drop_test_meshes([(box.vertices, box.faces), (np.zeros((0, 3)), np.zeros((0, 3), int))],
                               [pose(), pose()], backend="mujoco")
    row = settling_check(ok, DropTestConfig(), "convex hull")
    assert row["passed"] is True and row["value"] == ok.drift_m and row["threshold"] == 0.03
    assert row["method"] == "convex hull" and row["status"] == "run"
    row = settling_check(bad)
    assert row["passed"] is False and row["status"] == "failed" and row["reason"] == bad.error


def test_auto_backend_is_the_c_library_without_an_accelerator():
    import jax

    from phirie_jax.construct.physics.droptest import resolve_backend

    from phirie_jax.construct.physics.droptest import AUTO_BATCH_MIN

    assert resolve_backend("auto", 4) == "mujoco"                  # a few candidates: no compile pays
    if jax.default_backend() == "cpu":
        assert resolve_backend("auto", AUTO_BATCH_MIN) == "mujoco"
    else:
        assert resolve_backend("auto", AUTO_BATCH_MIN) in ("mjx", "warp")
    assert resolve_backend("mjx") == "mjx" and resolve_backend("mujoco") == "mujoco"
    with pytest.raises(ValueError, match="backend"):
        DropTestConfig(backend="bullet")
    with pytest.raises(ValueError, match="max_hull_vertices"):
        PhysicsConfig(max_hull_vertices=128)
