"""Mesh repair, bad meshes, CoACD parts within the vertex budget, hull decimation, fallback."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import Delaunay

from phirie_jax.construct.physics import collision
from phirie_jax.construct.physics.collision import MeshError, collision_from_mesh, convex_part, ghost_part, repair_mesh
from phirie_jax.construct.physics.config import CoacdConfig, PhysicsConfig

# CoACD with lighter search settings: the same algorithm, seconds instead of tens of seconds
FAST = PhysicsConfig(coacd=CoacdConfig(resolution=1000, preprocess_resolution=30, mcts_iterations=60, mcts_nodes=10))
VOLUME_RTOL = 1e-9


def annulus():
    return trimesh.creation.annulus(r_min=0.03, r_max=0.05, height=0.02, sections=48)


def test_coacd_splits_an_annulus_into_several_parts_within_the_vertex_budget():
    mesh = annulus()
    result = collision_from_mesh(mesh.vertices, mesh.faces, FAST)
    report = result.report
    assert report["method"] == "coacd" and "fallback" not in report
    assert 4 <= report["parts"] == len(result.parts) <= FAST.max_parts      # a ring is no single convex part
    assert all(4 <= len(p.vertices) <= FAST.max_hull_vertices for p in result.parts)
    assert all(p.volume > 0 for p in result.parts)
    # the parts cover the ring: about its volume, and none fills the hole
    assert 0.9 <= report["hull_volume_ratio"] <= 1.3
    centre_inside = [Delaunay(p.vertices).find_simplex([[0.0, 0.0, 0.0]])[0] >= 0 for p in result.parts]
    assert not any(centre_inside)
    assert report["time_s"] > 0 and report["repair"]["watertight"]
    assert report["coacd"]["tier"] == "concave" and report["coacd"]["threshold"] >= FAST.coacd.threshold


def test_a_coacd_failure_falls_back_to_the_convex_hull_and_says_so(monkeypatch):
    def broken(mesh, config, settings=None):
        raise RuntimeError("simulated CoACD crash")

    monkeypatch.setattr(collision, "_coacd_parts", broken)
    mesh = annulus()
    result = collision_from_mesh(mesh.vertices, mesh.faces, FAST)
    assert result.report["method"] == "convex_hull" and "simulated CoACD crash" in result.report["fallback"]
    assert len(result.parts) == 1 and len(result.parts[0].vertices) <= FAST.max_hull_vertices
    assert result.report["hull_volume_ratio"] > 1.0   # the hull fills the hole


def unit_box_soup(flip_every: int = 3):
    """A box as a triangle soup (every triangle its own vertices) with some triangles flipped."""
    box = trimesh.creation.box([0.1, 0.2, 0.3])
    tri = box.triangles.copy()
    tri[::flip_every] = tri[::flip_every, ::-1]
    return tri.reshape(-1, 3), np.arange(len(tri) * 3).reshape(-1, 3), box.volume


def test_repair_merges_vertices_and_fixes_winding():
    verts, faces, volume = unit_box_soup()
    mesh = repair_mesh(verts, faces)
    assert len(mesh.vertices) == 8 and len(mesh.faces) == 12 and mesh.watertight
    assert mesh.volume == pytest.approx(volume, rel=VOLUME_RTOL)
    assert trimesh.Trimesh(mesh.vertices, mesh.faces).volume == pytest.approx(volume, rel=VOLUME_RTOL)  # outward


def test_repair_simplifies_to_the_triangle_budget():
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.05)      # 20480 triangles
    config = PhysicsConfig(max_triangles=2000)
    mesh = repair_mesh(sphere.vertices, sphere.faces, config)
    assert len(mesh.faces) <= 2000 and mesh.report["simplified_to"] == len(mesh.faces)
    assert mesh.volume == pytest.approx(sphere.volume, rel=0.02)


def fin_mesh():
    """A closed box with one extra triangle on an edge: that edge has three triangles."""
    box = trimesh.creation.box([0.1, 0.1, 0.1])
    v = box.vertices
    edge = next(e for e in box.edges_unique if v[e[0], 2] > 0 and v[e[1], 2] > 0 and v[e[0], 1] == v[e[1], 1])
    apex = box.vertices[edge].mean(0) + [0.0, 0.0, 0.2]
    verts = np.vstack([box.vertices, apex])
    faces = np.vstack([box.faces, [edge[0], edge[1], len(box.vertices)]])
    return verts, faces


@pytest.mark.parametrize("name, mesh, reason", [
    ("empty", (np.zeros((0, 3)), np.zeros((0, 3), int)), "empty mesh"),
    ("degenerate", (np.zeros((3, 3)), np.array([[0, 1, 2]])), "empty mesh"),
    ("non-manifold", fin_mesh(), "non-manifold"),
    ("flat", (np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0.1, 0.1, 0]]), np.array([[0, 1, 2], [1, 3, 2]])),
     "zero volume"),
    ("nan", (np.array([[0, 0, 0], [1, 0, 0], [np.nan, 1, 0]]), np.array([[0, 1, 2]])), "non-finite"),
    ("bad index", (np.zeros((3, 3)), np.array([[0, 1, 7]])), "outside"),
])
def test_bad_meshes_raise_a_reason(name, mesh, reason):
    with pytest.raises(MeshError, match=reason):
        collision_from_mesh(*mesh)


def test_hull_decimation_stays_within_budget_and_inside_the_hull():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(2000, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)                # 2000 hull vertices
    part = convex_part(points, 64)
    assert len(part.vertices) <= 64
    # the decimated vertices are original points, so the part lies inside the original hull
    assert np.all(np.min(np.linalg.norm(part.vertices[:, None] - points[None], axis=-1), axis=1) < 1e-12)
    assert 0.8 * (4 / 3 * np.pi) < part.volume < 4 / 3 * np.pi
    assert trimesh.Trimesh(part.vertices, part.faces).volume == pytest.approx(part.volume)   # outward wound
    assert convex_part(points[:, :2].repeat(2, axis=1)[:, :3] * [1, 1, 0], 64) is None      # flat → None


def test_a_ghost_part_lies_strictly_inside_its_part():
    part = convex_part(trimesh.creation.cone(0.04, 0.12, sections=16).vertices, 64)
    ghost = ghost_part(part)
    assert np.all(Delaunay(part.vertices).find_simplex(ghost.vertices) >= 0)
    assert ghost.vertices[:, 2].min() > part.vertices[:, 2].min() + 1e-3


def test_repair_closes_a_hole_and_keeps_the_volume():
    box = trimesh.creation.box([0.1, 0.2, 0.3])
    top = np.flatnonzero(box.triangles_center[:, 2] > 0.149)
    faces = np.delete(box.faces, top, axis=0)[:, ::-1]        # open and inside out
    mesh = repair_mesh(box.vertices, faces)
    assert mesh.watertight and mesh.report["holes_filled"]
    assert mesh.volume == pytest.approx(box.volume, rel=VOLUME_RTOL)
    assert trimesh.Trimesh(mesh.vertices, mesh.faces).volume > 0


def test_orientation_fixes_flipped_triangles_and_leaves_consistent_ones_alone():
    from phirie_jax.construct.physics.collision import orient_faces

    sphere = trimesh.creation.icosphere(subdivisions=2)
    assert np.array_equal(orient_faces(sphere.faces), sphere.faces)       # already consistent: unchanged
    faces = sphere.faces.copy()
    flipped = np.random.default_rng(0).random(len(faces)) < 0.3
    faces[flipped] = faces[flipped, ::-1]
    fixed = orient_faces(faces)
    directed = np.concatenate([fixed[:, [0, 1]], fixed[:, [1, 2]], fixed[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed)              # every shared edge both ways
    same = np.all(fixed == sphere.faces, axis=1)
    assert same.all() or (~same).all()                                    # the sphere's winding, or all reversed


def test_coacd_settings_follow_the_objects_size_and_complexity():
    from phirie_jax.construct.physics.collision import coacd_settings
    from phirie_jax.construct.physics.config import AdaptiveCoacd

    config = PhysicsConfig()
    ring = repair_mesh(*annulus_arrays(0.03, 0.05))                       # solidity 0.64: a real concavity
    ball = repair_mesh(*sphere_arrays(0.04))                               # nearly convex
    big_ring = repair_mesh(*annulus_arrays(0.15, 0.25))
    concave, convex, large = coacd_settings(ring, config), coacd_settings(ball, config), coacd_settings(big_ring, config)
    assert concave.tier == "concave" and convex.tier == "nearly convex" and large.tier == "concave"
    assert concave.solidity == pytest.approx(1 - 0.03**2 / 0.05**2, rel=0.02)
    assert convex.threshold == config.coacd.adaptive.convex_threshold
    # the absolute tolerance: the 10 cm ring stops at 2 · 3 mm / 10 cm, the 50 cm one at the base threshold
    assert concave.threshold == pytest.approx(2 * config.coacd.adaptive.tolerance / 0.1, rel=1e-3)
    assert large.threshold == config.coacd.threshold
    assert concave.mcts_iterations == config.coacd.adaptive.mcts_iterations < config.coacd.mcts_iterations
    assert concave.resolution == config.coacd.adaptive.resolution < config.coacd.resolution
    raised = PhysicsConfig(coacd=CoacdConfig(adaptive=AdaptiveCoacd(concave_threshold=0.1)))  # a floor of their own
    assert coacd_settings(ring, raised).threshold == coacd_settings(big_ring, raised).threshold == 0.1
    assert coacd_settings(ball, raised).threshold == convex.threshold
    fixed = coacd_settings(ring, PhysicsConfig(coacd=CoacdConfig(adaptive=AdaptiveCoacd(enabled=False))))
    assert (fixed.tier, fixed.threshold, fixed.mcts_iterations, fixed.resolution, fixed.max_triangles) == (
        "fixed", config.coacd.threshold, config.coacd.mcts_iterations, config.coacd.resolution, 0)


def test_coacd_decomposes_a_simplified_input_and_keeps_the_repaired_volume(monkeypatch):
    from phirie_jax.construct.physics.config import AdaptiveCoacd

    seen = {}

    def recording(mesh, config, settings=None):
        seen["triangles"] = len(mesh.faces)
        return [mesh.vertices]

    monkeypatch.setattr(collision, "_coacd_parts", recording)
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.05)     # 5120 triangles
    config = PhysicsConfig(coacd=CoacdConfig(adaptive=AdaptiveCoacd(max_triangles=1000)))
    result = collision_from_mesh(sphere.vertices, sphere.faces, config)
    assert seen["triangles"] <= 1000 and result.report["coacd"]["max_triangles"] == 1000
    assert result.report["mesh_volume"] == pytest.approx(sphere.volume, rel=1e-9)
    # one part: the 64-vertex hull of the simplified sphere, inside it, over the repaired sphere's volume
    assert result.report["hull_volume_ratio"] == pytest.approx(result.parts[0].volume / sphere.volume, rel=1e-9)
    assert 0.85 < result.report["hull_volume_ratio"] < 1.0


def annulus_arrays(r_min: float, r_max: float):
    mesh = trimesh.creation.annulus(r_min=r_min, r_max=r_max, height=0.02, sections=48)
    return mesh.vertices, mesh.faces


def sphere_arrays(radius: float):
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    return mesh.vertices, mesh.faces


def box_corners(low, size=(1.0, 1.0, 1.0)) -> np.ndarray:
    low, size = np.asarray(low, np.float64), np.asarray(size, np.float64)
    return low + size * np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], np.float64)


def inside_hull(points: np.ndarray, part: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    from scipy.spatial import ConvexHull

    hull = ConvexHull(part)
    return np.all(points @ hull.equations[:, :3].T + hull.equations[:, 3] <= tol, axis=1)


def reference_merge(parts: list[np.ndarray], count: int) -> list[np.ndarray]:
    """merge_parts without its cache: every pair's cost recomputed at every step."""
    from scipy.spatial import ConvexHull

    parts = [np.asarray(p, np.float64) for p in parts]
    while len(parts) > count:
        best = None
        for i in range(len(parts)):
            for j in range(i + 1, len(parts)):
                joint = ConvexHull(np.concatenate([parts[i], parts[j]]))
                gap = (joint.volume - ConvexHull(parts[i]).volume - ConvexHull(parts[j]).volume) / joint.area
                if best is None or gap < best[0]:
                    best = (gap, i, j)
        _, i, j = best
        joint = np.concatenate([parts[i], parts[j]])
        parts[i] = joint[ConvexHull(joint).vertices]
        del parts[j]
    return parts


def test_merging_joins_the_parts_that_leave_no_gap_first():
    cubes = [box_corners((0, 0, 0)), box_corners((10, 0, 0)), box_corners((1, 0, 0)), box_corners((11, 0, 0))]
    merged = collision.merge_parts(cubes, 2)
    spans = sorted((p[:, 0].min(), p[:, 0].max()) for p in merged)
    assert spans == [(0.0, 2.0), (10.0, 12.0)]                          # the touching pairs, no bridge
    assert [collision._hull_volume(p) for p in merged] == pytest.approx([2.0, 2.0])
    assert len(collision.merge_parts(cubes, 4)) == 4 and len(collision.merge_parts(cubes[:3], 5)) == 3


def test_merged_parts_hold_their_inputs_and_equal_the_slow_reference():
    rng = np.random.default_rng(3)
    parts = [rng.normal(centre, 0.15, (10, 3)) for centre in rng.uniform(-1, 1, (9, 3))]
    merged = collision.merge_parts(parts, 4)
    reference = reference_merge(parts, 4)
    assert len(merged) == len(reference) == 4
    for ours, slow in zip(merged, reference):
        assert np.array_equal(np.unique(ours, axis=0), np.unique(slow, axis=0))
    for part in parts:                                                    # every input point in a merged hull
        assert any(inside_hull(part, m).all() for m in merged)


def test_a_ring_merged_to_few_parts_keeps_its_hole():
    mesh = annulus()
    config = PhysicsConfig(coacd=FAST.coacd, max_parts=4)
    result = collision_from_mesh(mesh.vertices, mesh.faces, config)
    assert result.report["method"] == "coacd" and result.report["parts"] <= 4
    centre_inside = [Delaunay(p.vertices).find_simplex([[0.0, 0.0, 0.0]])[0] >= 0 for p in result.parts]
    assert not any(centre_inside)
