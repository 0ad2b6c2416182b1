"""Every candidate is drop-tested before ranking; an unstable placement ranks below a stable one."""

from __future__ import annotations

import numpy as np
import trimesh

from phirie_jax.construct.objects.checks import rank
from phirie_jax.construct.objects.stage import settle_candidates
from phirie_jax.construct.physics.config import PhysicsConfig
from phirie_jax.construct.physics.settling import candidate_settler


class _Mesh:
    def __init__(self, name, mesh):
        self.name, self.vertices, self.faces = name, np.asarray(mesh.vertices), np.asarray(mesh.faces)


def _entry(name, pose, residual):
    checks = {k: {"value": 0.0, "threshold": 1.0, "passed": True} for k in ("registration", "scale", "support",
                                                                          "collision")}
    checks["registration"]["value"] = residual
    checks["settling"] = {"value": None, "threshold": 0.03, "passed": None, "status": "not_run"}
    return {"name": name, "status": "ok", "pose": pose, "checks": checks, "priority": 0}


def test_a_cone_on_its_tip_ranks_below_an_upright_box_despite_a_better_residual():
    cone = trimesh.creation.cone(radius=0.04, height=0.12)
    tip_down = np.eye(4)
    tilt = trimesh.transformations.rotation_matrix(np.deg2rad(5), [1, 0, 0])[:3, :3]
    tip_down[:3, :3] = tilt @ np.diag([1.0, -1.0, -1.0])    # apex at the bottom, 5° off balance
    tip_down[:3, 3] = [0.0, 0.0, 0.12]
    box = trimesh.creation.box(extents=[0.06, 0.06, 0.1])
    upright = np.eye(4)
    upright[2, 3] = 0.05
    entries = [_entry("cone", tip_down, residual=0.001), _entry("box", upright, residual=0.005)]
    settle_candidates(entries, [_Mesh("cone", cone), _Mesh("box", box)], np.array([0.0, 0.0, 1.0]), None,
                      candidate_settler(PhysicsConfig()))
    by_name = {e["name"]: e for e in entries}
    assert by_name["cone"]["checks"]["settling"]["passed"] is False
    assert by_name["cone"]["checks"]["settling"]["value"] >= 0.03
    assert by_name["box"]["checks"]["settling"]["passed"] is True
    assert [e["name"] for e in rank(entries)] == ["box", "cone"]
