"""Raycaster visibility queries on a closed mesh: the side a camera sees, what it sees through."""

import numpy as np
import trimesh

from phirie_jax.io.camera import intrinsics_matrix
from phirie_jax.observe.raycast import Raycaster
from phirie_jax.synthetic.scene import look_at
from phirie_jax.types import Camera

TOLERANCE = 0.005


def _camera_on_x() -> Camera:
    return Camera("x", intrinsics_matrix(100.0, 100.0, 64, 64), look_at(np.array([1.0, 0, 0]), np.zeros(3),
                                                                        up=(0.0, 0.0, 1.0)), 128, 128)


def test_the_side_a_camera_sees_and_the_side_it_does_not():
    box = trimesh.creation.box(extents=[0.2, 0.2, 0.2])
    caster = Raycaster(box.vertices, box.faces)
    rng = np.random.default_rng(1)
    yz = rng.uniform(-0.08, 0.08, (50, 2))
    front = np.column_stack([np.full(50, 0.1), yz])           # the face towards the camera
    back = np.column_stack([np.full(50, -0.1), yz])           # behind the box from the camera
    in_front = np.column_stack([np.full(50, 0.3), yz])        # free space between camera and box
    cam = _camera_on_x()
    assert caster.faces_camera(front, cam, TOLERANCE).all()
    assert not caster.faces_camera(back, cam, TOLERANCE).any()
    assert caster.faces_camera(in_front, cam, TOLERANCE).all()
    # seen through: only the free-space points (the camera's ray goes on past them to the box)
    assert caster.seen_through(in_front, cam, TOLERANCE).all()
    assert not caster.seen_through(front, cam, TOLERANCE).any()
    assert not caster.seen_through(back, cam, TOLERANCE).any()
