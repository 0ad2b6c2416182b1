"""Check tables and the lexicographic ranking on hand-built tables."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from phirie_jax.construct.objects.checks import (
    candidate_checks,
    check,
    failed,
    first_by_priority,
    hull_volume,
    kept_reason,
    mount_check,
    mount_of,
    not_run,
    rank,
    rank_key,
    residual_threshold,
)
from phirie_jax.construct.objects.config import ObjectsConfig
from phirie_jax.construct.objects.register import observed_size
from phirie_jax.observe.support import Wall, is_wall


def table(residual=0.005, scale=0.05, support=0.97, collision=True, settling=None, settling_passed=None):
    return {"registration": check(residual, 0.01, residual <= 0.01), "scale": check(scale, 0.15, scale <= 0.15),
            "support": check(support, 0.9, support >= 0.9), "collision": check(1e-3 if collision else 0.0, 1e-7, collision),
            "settling": check(settling, 0.03, settling_passed)}


def entry(name, priority=0, **kw):
    return {"name": name, "priority": priority, "checks": table(**kw)}


def test_all_passing_beats_fewer_failures_beats_more_failures_whatever_the_residual():
    a = entry("a", residual=0.0099)                                 # passes everything
    b = entry("b", residual=0.002, support=0.5)                     # one failure, tiny residual
    c = entry("c", residual=0.001, support=0.5, scale=0.9)          # two failures, tinier residual
    assert [e["name"] for e in rank([c, b, a])] == ["a", "b", "c"]


def test_residual_then_scale_then_settling_then_priority_then_name():
    r1 = entry("r1", residual=0.004, scale=0.1)
    r2 = entry("r2", residual=0.006, scale=0.0)
    assert [e["name"] for e in rank([r2, r1])] == ["r1", "r2"]           # residual first
    s1 = entry("s1", residual=0.004, scale=0.01)
    s2 = entry("s2", residual=0.004, scale=0.02)
    assert [e["name"] for e in rank([s2, s1])] == ["s1", "s2"]           # then scale
    d1 = entry("d1", settling=0.01, settling_passed=True)
    d2 = entry("d2", settling=0.02, settling_passed=True)
    d3 = entry("d3")                                                     # not run ranks last
    assert [e["name"] for e in rank([d3, d2, d1])] == ["d1", "d2", "d3"]
    p1, p2 = entry("zz", priority=0), entry("aa", priority=1)
    assert [e["name"] for e in rank([p2, p1])] == ["zz", "aa"]           # pool priority
    n1, n2 = entry("a", priority=1), entry("b", priority=1)
    assert [e["name"] for e in rank([n2, n1])] == ["a", "b"]             # then the name: deterministic


def test_not_run_checks_neither_pass_nor_fail_and_invalid_entries_are_not_ranked():
    e = entry("x")
    assert failed(e["checks"]) == [] and not_run(e["checks"]) == ["settling"]
    assert rank_key(e)[:2] == (False, 0)
    assert rank([{"name": "broken", "priority": 0, "checks": {}}, e]) == [e]


def test_fixed_priority_takes_the_first_passing_candidate_in_pool_order():
    first_fails = entry("a", priority=0, support=0.5)
    second_passes = entry("b", priority=1, residual=0.009)
    third_better = entry("c", priority=2, residual=0.001)
    assert first_by_priority([third_better, second_passes, first_fails])["name"] == "b"
    assert first_by_priority([first_fails])["name"] == "a"       # nothing passes: the first valid one
    assert first_by_priority([]) is None


def test_candidate_checks_from_scores():
    config = ObjectsConfig()
    scores = {"energy": 0.005, "support": 0.99, "scale": 0.2, "scale_init": 0.2 * math.exp(0.3)}
    checks = candidate_checks(scores, 1.0, config)
    assert checks["registration"]["passed"] and checks["support"]["passed"]
    assert checks["scale"]["value"] == pytest.approx(0.3) and checks["scale"]["passed"] is False
    assert checks["collision"]["value"] == pytest.approx(0.2**3) and checks["collision"]["passed"]
    assert checks["settling"] == {"value": None, "threshold": config.settle_threshold, "passed": None,
                                  "status": "not_run", "reason": checks["settling"]["reason"]}
    assert failed(checks) == ["scale"]


def test_the_registration_bound_grows_with_the_object_past_its_absolute_floor():
    config = ObjectsConfig()
    scores = {"energy": 0.015, "support": 0.99, "scale": 1.0, "scale_init": 1.0}
    small = candidate_checks(scores, 1.0, config, observed_size=0.2)      # 4 % of 20 cm < 1 cm
    large = candidate_checks(scores, 1.0, config, observed_size=0.5)      # 4 % of 50 cm = 2 cm
    assert small["registration"]["threshold"] == config.max_residual and not small["registration"]["passed"]
    assert large["registration"]["threshold"] == pytest.approx(config.max_relative_residual * 0.5)
    assert large["registration"]["passed"] and large["registration"]["observed_size"] == 0.5
    assert residual_threshold(0.0, config) == config.max_residual
    strict = dataclasses.replace(config, max_relative_residual=0.0)
    assert not candidate_checks(scores, 1.0, strict, observed_size=0.5)["registration"]["passed"]


def test_the_observed_size_ignores_strays():
    rng = np.random.default_rng(0)
    box = rng.uniform(0.0, [0.3, 0.4, 0.0], (5000, 3))
    strays = np.concatenate([box, [[5.0, 5.0, 5.0]] * 20])
    assert observed_size(box) == pytest.approx(0.5, rel=0.05)
    assert observed_size(strays) == pytest.approx(observed_size(box), rel=0.02)
    assert observed_size(np.zeros((0, 3))) == 0.0


def test_hull_volume_of_a_cube_and_of_a_flat_set():
    import itertools

    cube = list(itertools.product([0, 2], repeat=3))
    assert hull_volume(cube) == pytest.approx(8.0)
    assert hull_volume([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]) == 0.0


def test_automatically_discovered_instance_failing_registration_is_rejected():
    from phirie_jax.construct.objects.checks import discovered_rejection

    assert "registration" in discovered_rejection("auto", ["registration", "scale"])
    assert discovered_rejection("auto", ["scale"]) is None          # kept (its failed checks recorded)
    assert discovered_rejection("auto", []) is None
    assert "0.043 m above the support" in discovered_rejection("auto", [], 0.0431, 0.03)   # a floater
    assert discovered_rejection("auto", [], 0.01, 0.03) is None
    assert discovered_rejection("masks", [], 0.12, 0.03) is None                           # user evidence: kept
    for source in ("files", "external", "prompt", None):            # user evidence is kept
        assert discovered_rejection(source, ["registration"]) is None


def test_a_hanging_object_that_fails_settling_is_said_to_hang():
    from phirie_jax.construct.objects.generators import InstanceInput
    from phirie_jax.construct.objects.stage import base_gap
    from phirie_jax.frame.gravity import gravity_frame
    from phirie_jax.observe.support import Support

    rng = np.random.default_rng(0)
    frame = gravity_frame(np.array([0.0, 0.0, 1.0]), "test")
    support = Support(0.0, "surface", 100, np.array([0.0, 0.0, 1.0]))
    standing = InstanceInput(1, rng.uniform([0, 0, 0.0], [0.1, 0.1, 0.2], (2000, 3)), frame, support, (), (), ())
    hanging = InstanceInput(1, rng.uniform([0, 0, 0.09], [0.1, 0.1, 0.3], (2000, 3)), frame, support, (), (), ())
    assert base_gap(hanging) == pytest.approx(0.09, abs=0.005) and base_gap(standing) == pytest.approx(0.0, abs=0.005)
    assert "0.09 m above the support" in kept_reason(["settling"], base_gap(hanging), 0.03)
    assert "hangs" not in kept_reason(["settling"], base_gap(standing), 0.03)
    assert "hangs" not in kept_reason(["registration"], base_gap(hanging), 0.03)
    assert "hangs" not in kept_reason(["settling"], None, 0.03)      # a record from before the gap was kept
    assert kept_reason([], base_gap(hanging), 0.03) is None


def _wall(gap: float) -> Wall:
    """A wall at x = −0.2 facing +x (towards the object), the object's Gaussians ``gap`` in front of it."""
    return Wall(np.array([1.0, 0.0, 0.0]), -0.2, gap, "test")


def test_a_hanging_object_near_a_wall_is_mounted_and_nothing_else_is():
    config, wall = ObjectsConfig(), _wall(0.02)
    assert mount_of(wall, 0.12, config) is wall                               # the fox: 0.12 m up, 2 cm from its wall
    assert mount_of(_wall(0.02), 0.01, config) is None                        # it stands on its support
    assert mount_of(_wall(0.08), 0.12, config) is None                        # the wall is too far to hold it
    assert mount_of(None, 0.12, config) is None                               # no wall was found behind it
    assert "hangs" not in kept_reason(["settling"], 0.12, 0.03, mounted=True)  # its weld failed, not the missing one


def test_the_mount_check_asks_the_placed_asset_to_reach_its_wall():
    config = ObjectsConfig()
    near = np.array([[-0.19, 0.0, 0.5], [0.1, 0.0, 0.5]])                     # 1 cm from the wall
    far = near + [0.05, 0.0, 0.0]                                             # 6 cm from it
    into = near - [0.03, 0.0, 0.0]                                            # 2 cm into it: it touches
    assert mount_check(near, _wall(0.02), config)["value"] == pytest.approx(0.01)
    assert mount_check(near, _wall(0.02), config)["passed"]
    assert not mount_check(far, _wall(0.02), config)["passed"]
    assert mount_check(into, _wall(0.02), config)["value"] == 0.0
    assert not mount_check(np.zeros((0, 3)), _wall(0.02), config)["passed"]


def test_a_wall_record_round_trips_and_turns_with_its_frame():
    wall = Wall(np.array([0.6, 0.8, 0.0]), 0.25, 0.0123, "a plane")
    assert Wall.from_record(wall.as_record()).as_record() == wall.as_record()
    assert Wall.from_record(None) is None
    points = np.array([[1.0, 2.0, 3.0], [-0.5, 0.1, 0.0]])
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(wall.in_frame(turn).distance(points @ turn.T), wall.distance(points))
    assert is_wall([0.95, 0.0, 0.3]) and not is_wall([0.5, 0.0, 0.85])      # 17.5° vs 58° from horizontal
