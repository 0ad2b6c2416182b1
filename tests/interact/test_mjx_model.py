"""The batched worlds' collision model: one convex hull per multi-part object, nothing else changed."""

from __future__ import annotations

import itertools

import mujoco
import numpy as np
import pytest

from phirie_jax.interact.environment import Environment, load_spec
from phirie_jax.interact.mjx_model import HULL_SUFFIX, body_frame_vertices, hull_collision_spec, multi_part
from phirie_jax.types import GaussianSplatData

SETTLE_AGREEMENT = 1e-3  # m: the hull and the parts rest the same where the bottom is convex


def box_vertices(lo, hi) -> str:
    return " ".join(f"{x} {y} {z}" for x, y, z in itertools.product(*zip(lo, hi)))


# object_1: an L of two mesh boxes (its hull is the 8-vertex box of their union, minus a notch);
# object_2: one mesh box (already a single part: left alone)
SCENE = f"""
<mujoco>
  <option timestep="{1 / 240}"/>
  <asset>
    <mesh name="object_1_part_00" vertex="{box_vertices((-0.05, -0.03, 0), (0.05, 0.03, 0.04))}"/>
    <mesh name="object_1_part_01" vertex="{box_vertices((0.01, -0.03, 0.04), (0.05, 0.03, 0.12))}"/>
    <mesh name="object_2_part_00" vertex="{box_vertices((-0.03, -0.03, 0), (0.03, 0.03, 0.06))}"/>
  </asset>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 0.1" friction="0.7"/>
    <body name="object_1" pos="0 0 0.001"><freejoint/>
      <inertial pos="0.02 0 0.04" mass="0.3" diaginertia="4e-4 5e-4 3e-4"/>
      <geom name="object_1_part_00" type="mesh" mesh="object_1_part_00" friction="0.7"/>
      <geom name="object_1_part_01" type="mesh" mesh="object_1_part_01" friction="0.7"/>
    </body>
    <body name="object_2" pos="0.3 0 0.001"><freejoint/>
      <inertial pos="0 0 0.03" mass="0.3" diaginertia="2e-4 2e-4 2e-4"/>
      <geom name="object_2_part_00" type="mesh" mesh="object_2_part_00"/>
    </body>
  </worldbody>
</mujoco>"""


@pytest.fixture
def scene(tmp_path):
    (tmp_path / "scene.xml").write_text(SCENE)
    model = load_spec(tmp_path).compile()
    hull = hull_collision_spec(load_spec(tmp_path), model, ["object_1"]).compile()
    return tmp_path, model, hull


def colliding(model, body: str) -> list[str]:
    b = model.body(body).id
    return [model.geom(g).name for g in range(model.ngeom)
            if model.geom_bodyid[g] == b and (model.geom_contype[g] or model.geom_conaffinity[g])]


def test_only_multi_part_bodies_are_merged(scene):
    _, model, _ = scene
    assert multi_part(model, model.body("object_1").id)
    assert not multi_part(model, model.body("object_2").id)


def test_each_merged_object_collides_through_one_hull_with_unchanged_mass(scene):
    _, model, hull = scene
    assert colliding(hull, "object_1") == ["object_1" + HULL_SUFFIX]
    assert colliding(hull, "object_2") == colliding(model, "object_2") == ["object_2_part_00"]
    for field in ("body_mass", "body_inertia", "body_ipos", "body_iquat", "body_pos"):
        np.testing.assert_allclose(getattr(hull, field), getattr(model, field), err_msg=field)
    assert (hull.nq, hull.nv, hull.nbody) == (model.nq, model.nv, model.nbody)


def test_the_hull_is_the_convex_hull_of_the_parts(scene):
    from scipy.spatial import ConvexHull

    _, model, hull = scene
    parts = body_frame_vertices(model, model.body("object_1").id)
    g = hull.geom("object_1" + HULL_SUFFIX).id
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, hull.geom_quat[g])
    mesh = hull.geom_dataid[g]
    verts = hull.mesh_vert[hull.mesh_vertadr[mesh]:hull.mesh_vertadr[mesh] + hull.mesh_vertnum[mesh]]
    verts = verts @ rot.reshape(3, 3).T + hull.geom_pos[g]
    # every hull vertex is a part vertex, and every part vertex lies inside the hull
    assert np.min(np.linalg.norm(verts[:, None] - parts[None], axis=-1), axis=1).max() < 1e-6
    planes = ConvexHull(verts).equations  # n·x + d ≤ 0 inside
    assert (parts @ planes[:, :3].T + planes[:, 3]).max() < 1e-6
    # the notch of the L is inside the hull, outside the parts
    assert (np.array([-0.01, 0.0, 0.06]) @ planes[:, :3].T + planes[:, 3]).max() < 0


def test_resting_on_a_flat_bottom_is_unchanged(scene):
    _, model, hull = scene
    finals = []
    for m in (model, hull):
        data = mujoco.MjData(m)
        mujoco.mj_step(m, data, 480)
        finals.append(data.xpos.copy())
    np.testing.assert_allclose(finals[0], finals[1], atol=SETTLE_AGREEMENT)


def test_batched_environment_names_an_unknown_collision_model(scene):
    from phirie_jax.interact.batched import BatchedEnvironment

    out, model, _ = scene
    empty = GaussianSplatData(np.zeros((0, 3), np.float32), np.zeros((0, 4), np.float32),
                              np.zeros((0, 3), np.float32), np.zeros(0, np.float32), np.zeros((0, 1, 3), np.float32))
    env = Environment(out, model, empty, [], [])
    with pytest.raises(ValueError, match="collision 'boxes'"):
        BatchedEnvironment(env, 2, collision="boxes")


def _splats(n: int, seed: int) -> GaussianSplatData:
    rng = np.random.default_rng(seed)
    return GaussianSplatData(rng.uniform(-0.03, 0.03, (n, 3)).astype(np.float32),
                             np.tile(np.float32([1, 0, 0, 0]), (n, 1)), np.full((n, 3), -5.0, np.float32),
                             np.zeros(n, np.float32), np.zeros((n, 1, 3), np.float32))


def test_batched_worlds_on_the_hull_model_step_like_mujoco_c_on_it(scene):
    from phirie_jax.interact.batched import BatchedEnvironment

    out, model, _ = scene
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    objects = [(k, np.eye(4), _splats(8, k)) for k in (1, 2)]
    env = Environment(out, model, _splats(8, 9), objects, [])
    batch = BatchedEnvironment(env, 2)
    assert colliding(batch.mj_model, "object_1") == ["object_1" + HULL_SUFFIX]
    throws = np.zeros((2, model.nv))
    throws[1, 0:3] = [0.3, 0.0, 0.6]   # world 1: the L thrown
    batch.set_velocities(throws)
    batch.step(96)
    for world in range(2):
        c = mujoco.MjData(batch.mj_model)
        c.qvel[:] = throws[world]
        mujoco.mj_step(batch.mj_model, c, 96)
        np.testing.assert_allclose(np.asarray(batch.data.xpos[world]), c.xpos, atol=3e-3)
    body = model.body("object_1").id
    assert np.linalg.norm(np.asarray(batch.data.xpos[1, body] - batch.data.xpos[0, body])) > 0.02
