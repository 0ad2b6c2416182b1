"""The Warp worlds' experiments run end to end on the CPU at tiny sizes: the world-steps benchmark
(Warp against the MJX worlds in one run) and the robot evaluation in Warp worlds (success as
MuJoCo C gives it on the same placements)."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("mujoco_warp", reason="MuJoCo Warp not installed (pip install 'phirie_jax[warp]')")

REST_TOL = 1e-3   # m: world 0 rests; Warp (float32) against MuJoCo C after the same steps


def test_bench_warp_worlds_reports_world_steps_and_checks_world_zero(converted, tmp_path):
    from experiments import bench_warp_worlds

    out = tmp_path / "bench.json"
    bench_warp_worlds.main([str(converted[0]), "--worlds", "3", "--steps", "8", "--repeats", "1",
                            "--backends", "warp", "--out", str(out)])
    result = json.loads(out.read_text())
    warp = result["warp"]
    assert warp["collision"] == "parts" and warp["overflow_worlds"] == 0
    assert warp["world_steps_per_s"] > 0 and warp["run_s"] > 0 and warp["placements_shape"] == [3, 3, 4, 4]
    assert warp["world0_vs_c_max_position_m"] < REST_TOL


def test_throws_leave_world_zero_at_rest_and_move_only_objects(converted):
    import numpy as np

    from experiments.bench_warp_worlds import throws
    from phirie_jax.interact.environment import Environment

    env = Environment.load(converted[0])
    qvel = throws(env, 5, 0.5)
    assert qvel.shape == (5, env.model.nv) and not qvel[0].any()
    speeds = np.linalg.norm(qvel[1:].reshape(4, -1, 6)[..., :3], axis=-1)   # free joints only in this scene
    assert speeds.max() <= 0.5 + 1e-12 and speeds.min() > 0.0
    assert np.all(qvel[1:].reshape(4, -1, 6)[..., 2] >= 0.0), "thrown upwards, never into the support"


@pytest.mark.slow  # two whole episodes (2,592 steps) in Warp on the CPU: about a minute
def test_robot_eval_in_warp_worlds_agrees_with_mujoco_c(converted):
    from experiments.robot_eval import evaluate

    result = evaluate(converted[0], episodes=2, placement_range=0.03, seed=0, objects=[1], backend="warp")
    row = result["objects"][0]
    assert result["backend"] == "warp" and row["planned"] == 2
    assert row["warp_success_rate"] == row["c_success_rate"] == 1.0 and row["agree"] == 1.0
    assert row["warp_overflow_worlds"] == 0 and result["warp_episodes_per_s"] > 0
    assert max(abs(a - b) for a, b in zip(row["warp_distance_m"], row["c_distance_m"])) < 0.005
