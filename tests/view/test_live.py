"""The viewer's live simulation on a converted folder (no browser): play / pause / reset, shots
along a ray, drags, and node motions that start at the identity."""

from __future__ import annotations

import numpy as np
import pytest

from phirie_jax.interact.environment import Environment
from phirie_jax.records import ObjectRecord
from phirie_jax.view.config import ViewConfig
from phirie_jax.view.live import LiveScene
from phirie_jax.view.panel import object_markdown
from tests.fixtures.box_scene import BOXES, converted_folder

SETTLED_M = 0.002     # a resting box moves less than this in half a second
DRAG_GAIN_M = 0.05    # a 15 cm drag brings the box at least this much closer


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return converted_folder(tmp_path_factory.mktemp("live"))


@pytest.fixture
def live(folder):
    return LiveScene(Environment.load(folder), ViewConfig(max_substeps=10_000))


def positions(live) -> dict[int, np.ndarray]:
    return {object_id: position for object_id, _, position in live.motions()}


def centre(live, object_id: int) -> np.ndarray:
    return live.env.placements()[live.object_ids.index(object_id)][:3, 3]


def test_motions_start_at_identity_and_resting_boxes_stay(live):
    assert sorted(live.object_ids) == sorted(BOXES)
    for _, wxyz, position in live.motions():
        assert np.allclose(np.abs(wxyz), [1, 0, 0, 0]) and np.allclose(position, 0)
    assert live.advance(0.5) == round(0.5 / live.env.timestep)
    assert all(np.linalg.norm(p) < SETTLED_M for p in positions(live).values())


def test_pause_holds_and_reset_returns_to_the_start(live):
    live.playing = False
    live.env.place(3, linear_velocity=(0.0, 0.0, 2.0))   # thrown up: 15 cm in 0.1 s
    assert live.advance(0.1) == 0
    assert all(np.linalg.norm(p) < 1e-12 for p in positions(live).values())
    live.playing = True
    live.advance(0.1)
    assert positions(live)[3][2] > 0.1
    live.reset()
    assert live.time == 0 and all(np.linalg.norm(p) < 1e-12 for p in positions(live).values())


def test_a_ray_through_an_object_shoots_it_and_a_miss_hits_nothing(live):
    target = centre(live, 3) + [0.0, 0.0, 0.04]
    origin = target + np.array([-0.5, 0.0, 0.2])
    shot = live.shoot(origin, target - origin, speed=2.0)
    assert shot["hit"] == 3
    mass = float(live.env.model.body_subtreemass[live.env.object(3).body_id])
    assert np.linalg.norm(shot["impulse"]) == pytest.approx(2.0 * mass)
    live.advance(0.25)
    moved = positions(live)
    assert moved[3][0] > 0.05 and np.linalg.norm(moved[7]) < SETTLED_M  # along the ray; the other stays
    miss = live.shoot(origin + [0.0, 0.0, 5.0], [0.0, 0.0, 1.0])
    assert miss["hit"] is None and [s["hit"] for s in live.shots] == [3, None]


def test_a_drag_pulls_the_object_towards_the_pointer_and_release_lets_go(live):
    start = centre(live, 7)
    grip = start + [0.0, 0.0, 0.05]
    goal = grip + [0.0, -0.15, 0.0]
    live.grab(7, grip)
    live.drag_to(7, goal)
    live.advance(1.0)
    body = live.env.object(7).body_id
    assert np.any(live.env.data.xfrc_applied[body] != 0)
    gained = np.linalg.norm(goal - start) - np.linalg.norm(goal - centre(live, 7))
    assert gained > DRAG_GAIN_M, gained
    assert np.linalg.norm(positions(live)[3]) < SETTLED_M   # only the grabbed one
    live.release(7)
    assert not live.grabs and np.all(live.env.data.xfrc_applied[body] == 0)


def test_the_panel_says_candidate_checks_drop_test_and_physics(folder):
    import json

    entry = ObjectRecord.from_json(json.loads((folder / "manifest.json").read_text())["objects"][0])
    text = object_markdown(entry)
    assert "candidate `box`" in text and "registration" in text and "settling" in text
    assert "drop test: stable" in text and f"mass {entry.mass:.3g} kg" in text and "1 convex parts" in text
    rejected = object_markdown(ObjectRecord.from_json({"id": 9, "status": "rejected", "candidate": None,
                                                       "reason": "registration residual too high", "drop_test": None}))
    assert "rejected" in rejected and "registration residual too high" in rejected and "not run" in rejected


def test_without_viser_the_command_says_how_to_get_it(folder, monkeypatch, capsys):
    import sys

    from phirie_jax.cli import main

    monkeypatch.setitem(sys.modules, "viser", None)  # import viser → ImportError
    assert main(["view", str(folder), "--port", "0"]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("phirie: error:") and "pip install 'phirie_jax[viewer]'" in error
    assert main(["view", str(folder), "--port", "70000"]) == 2
    assert "--port 70000: expected in [0, 65535]" in capsys.readouterr().err
