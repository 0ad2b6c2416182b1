"""Support geoms from object footprints and a scene surface, in a tilted scene frame too."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from phirie_jax.construct.physics.supports import FALLBACK_MARGIN, PlacedBody, fit_background

TABLE = (1.0, 0.6, 0.7)   # extent x, extent y, top height


def scene(rot=np.eye(3)):
    table = trimesh.creation.box([TABLE[0], TABLE[1], 0.04])
    table.apply_translation([0.2, -0.1, TABLE[2] - 0.02])
    floor = trimesh.creation.box([3.0, 3.0, 0.02])
    floor.apply_translation([0, 0, -0.01])
    surface = trimesh.util.concatenate([floor, table])
    surface.vertices = surface.vertices @ rot.T
    cube = trimesh.creation.box([0.05, 0.05, 0.05]).vertices
    bodies = [PlacedBody(1, (cube + [0.3, 0.0, TABLE[2] + 0.025]) @ rot.T, TABLE[2]),
              PlacedBody(2, (cube + [0.0, -0.2, TABLE[2] + 0.025]) @ rot.T, None),      # no support: lowest point
              PlacedBody(3, (cube + [1.2, 1.0, 0.025]) @ rot.T, 0.0)]                    # on the floor
    return surface, bodies


@pytest.mark.parametrize("rotvec", [(0.0, 0.0, 0.0), (0.5, -0.3, 1.0)])
def test_floor_plane_and_tabletop_box_in_any_scene_frame(rotvec):
    rot = Rotation.from_rotvec(rotvec).as_matrix()
    surface, bodies = scene(rot)
    geoms = {g.name: g for g in fit_background(bodies, rot[:, 2], surface)}
    assert sorted(geoms) == ["floor", "support_0"]
    floor, box = geoms["floor"], geoms["support_0"]
    assert floor.type == "plane" and abs(rot[:, 2] @ floor.pos) < 1e-9
    np.testing.assert_allclose(Rotation.from_quat(floor.quat, scalar_first=True).as_matrix()[:, 2], rot[:, 2],
                               atol=1e-9)
    top = rot.T @ box.pos + [0, 0, box.size[2]]
    assert top[2] == pytest.approx(TABLE[2], abs=1e-9)
    assert sorted(2 * box.size[:2]) == pytest.approx(sorted(TABLE[:2]), abs=0.05)
    np.testing.assert_allclose(top[:2], [0.2, -0.1], atol=0.03)
    assert "objects 1, 2" in box.source


def test_without_a_surface_the_box_covers_the_footprints_and_plane_mode_is_one_plane():
    _, bodies = scene()
    geoms = {g.name: g for g in fit_background(bodies, (0, 0, 1), None)}
    box = geoms["support_0"]
    assert "no surface" in box.source
    for b in bodies[:2]:
        local = Rotation.from_quat(box.quat, scalar_first=True).inv().apply(b.points - box.pos)
        assert np.all(np.abs(local[:, :2]) <= box.size[:2] - FALLBACK_MARGIN + 1e-9)
    only = fit_background(bodies, (0, 0, 1), None, mode="plane")
    assert [g.type for g in only] == ["plane"] and only[0].pos[2] == pytest.approx(0.0)


@pytest.mark.parametrize("rotvec", [(0.0, 0.0, 0.0), (0.5, -0.3, 1.0)])
def test_up_facing_triangles_are_the_tops_in_the_gravity_frame(rotvec):
    from phirie_jax.construct.physics.supports import UP_FACING_DEG, UpFacing

    rot = Rotation.from_rotvec(rotvec).as_matrix()
    surface, _ = scene(rot)
    up = UpFacing.of(surface, rot.T)                           # scene → gravity undoes the tilt
    # the slow reference: trimesh's unit face normals, taken back to the gravity frame
    normals = surface.face_normals @ rot
    wanted = np.flatnonzero(normals[:, 2] >= np.cos(np.radians(UP_FACING_DEG)))
    np.testing.assert_allclose(up.triangles, surface.triangles[wanted] @ rot, atol=1e-12)
    np.testing.assert_allclose(up.areas, surface.area_faces[wanted], rtol=1e-9)
    assert up.areas.sum() == pytest.approx(3.0 * 3.0 + TABLE[0] * TABLE[1])   # the floor's and the table's tops
    np.testing.assert_allclose(np.sort(np.unique(up.triangles[:, :, 2].round(9))), [0.0, TABLE[2]], atol=1e-9)
