"""MuJoCo Warp drop tests (``warp_batch``) against the MuJoCo C reference on the same models."""

import dataclasses

import numpy as np
import pytest

from phirie_jax.construct.physics import warp_batch
from phirie_jax.construct.physics.collision import hull_part
from phirie_jax.construct.physics.config import DropTestConfig
from phirie_jax.construct.physics.droptest import (
    body_from_parts,
    build_model,
    drop_test,
    run_reference,
    spawn_qpos,
)
from tests.fixtures import droptest_cases as cases

pytest.importorskip("mujoco_warp", reason="MuJoCo Warp not installed (pip install 'phirie_jax[warp]')")

QPOS_TOLERANCE = 2e-3   # m / quaternion units: float32 Warp vs float64 C after 240 steps of contact
# a shortened protocol (0.5 s + 0.5 s): the full one only repeats the same steps
SHORT = dataclasses.replace(DropTestConfig(), settle_time=0.5, free_time=0.5)


def _cases(count: int):
    chosen = cases.case_set(count, 3)
    return chosen, [body_from_parts((hull_part(c.vertices),), c.pose) for c in chosen]


def test_bank_model_holds_each_candidate_in_its_own_frame():
    _, bodies = _cases(4)
    models = [build_model(b, 4, SHORT) for b in bodies]      # ghost-padded to 4 parts
    bank, ids = warp_batch.bank_model(models, SHORT)
    assert ids.shape == (4, 4) and bank.nmesh == 16
    for n, m in enumerate(models):
        for p in range(4):
            mine, theirs = int(ids[n, p]), int(m.geom_dataid[1 + p])
            a = bank.mesh_vert[bank.mesh_vertadr[mine]: bank.mesh_vertadr[mine] + bank.mesh_vertnum[mine]]
            b = m.mesh_vert[m.mesh_vertadr[theirs]: m.mesh_vertadr[theirs] + m.mesh_vertnum[theirs]]
            # the same mesh frame: the candidate's geom frame places the bank's mesh too
            np.testing.assert_allclose(np.sort(a, axis=0), np.sort(b, axis=0), atol=1e-6)


def test_bank_refuses_mixed_buckets():
    _, bodies = _cases(2)
    with pytest.raises(ValueError, match="one bucket per batch"):
        warp_batch.bank_model([build_model(bodies[0], 1, SHORT), build_model(bodies[1], 4, SHORT)], SHORT)


def test_warp_follows_mujoco_c_and_gives_its_verdicts():
    chosen, bodies = _cases(6)
    models = [build_model(b, 1, SHORT) for b in bodies]
    qpos0 = np.stack([spawn_qpos(b) for b in bodies])
    result = warp_batch.run(models, qpos0, SHORT, device="cpu")
    assert result.free_steps_run == SHORT.free_steps and result.device == "cpu"
    for k, (m, q) in enumerate(zip(models, qpos0)):
        settled, final = run_reference(m, q, SHORT)
        np.testing.assert_allclose(result.settled[k], settled, atol=QPOS_TOLERANCE, err_msg=chosen[k].name)
        np.testing.assert_allclose(result.final[k], final, atol=QPOS_TOLERANCE, err_msg=chosen[k].name)
    ours = drop_test(bodies, SHORT, backend="warp")
    ref = drop_test(bodies, SHORT, backend="mujoco")
    assert [r.stable for r in ours] == [r.stable for r in ref]
    assert {r.backend for r in ours} == {"warp"}


def test_worlds_split_over_devices_give_the_states_of_one_batch():
    """Two parts on the CPU stand in for two GPUs: the split, the interleaved phases and the
    concatenation in world order, with and without the early exit."""
    import jax

    config = dataclasses.replace(SHORT, settle_time=0.1, free_time=0.25)   # kernel launches dominate on a CPU
    _, bodies = _cases(5)
    models = [build_model(b, 1, config) for b in bodies]
    qpos0 = np.stack([spawn_qpos(b) for b in bodies])
    assert warp_batch.warp_devices(jax.devices()) == ["cpu"]
    for early_exit in (False, True):
        whole = warp_batch.run(models, qpos0, config, early_exit, device="cpu")
        parts = warp_batch.prepare_split(models, qpos0, config, early_exit, devices=["cpu", "cpu"])
        assert [len(p.qpos0) for p in parts] == [3, 2]
        split = warp_batch.simulate_all(parts)
        assert split.device == "cpu,cpu" and split.free_steps_run == whole.free_steps_run
        np.testing.assert_array_equal(split.settled, whole.settled)
        np.testing.assert_array_equal(split.final, whole.final)
