"""The Interactive Environment: simulated poses drive the Gaussians, consistently."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kernels.gaussians import Sim3, concatenate, transform_gaussians
from phirie_jax.interact.environment import Environment
from phirie_jax.io.camera import intrinsics_matrix
from phirie_jax.render import render
from phirie_jax.synthetic.scene import look_at
from phirie_jax.types import Camera, GaussianSplatData

IMAGE_TOL = 2e-4        # float32 rasterization of identically placed Gaussians
CENTROID_TOL = 0.01     # the 1 cm
HALF = (0.05, 0.04, 0.05)
TOY = f"""
<mujoco>
  <option timestep="{1 / 240}"/>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 0.1" friction="0.5"/>
    <body name="object_1" pos="0 0 {HALF[2]}"><freejoint/>
      <geom type="box" size="{HALF[0]} {HALF[1]} {HALF[2]}" mass="0.3"/></body>
    <body name="object_2" pos="0.25 0.1 0.04" euler="0 0 30"><freejoint/>
      <geom type="box" size="0.03 0.03 0.04" mass="0.3"/></body>
  </worldbody>
</mujoco>"""


def box_gaussians(half, n, seed, degree=3, view_dependence=0.0) -> GaussianSplatData:
    """Flat Gaussians on a box surface, canonical (body) frame, with optional strong SH."""
    rng = np.random.default_rng(seed)
    face = rng.integers(6, size=n)
    pts = rng.uniform(-1, 1, (n, 3)) * half
    axis = face % 3
    pts[np.arange(n), axis] = np.where(face < 3, 1, -1) * np.asarray(half)[axis]
    sh = np.zeros((n, (degree + 1) ** 2, 3), np.float32)
    sh[:, 0] = rng.uniform(-1.5, 1.5, (n, 3))
    sh[:, 1:] = view_dependence * rng.normal(size=(n, (degree + 1) ** 2 - 1, 3))
    return GaussianSplatData(
        means=pts.astype(np.float32), quats=rng.normal(size=(n, 4)).astype(np.float32),
        log_scales=np.full((n, 3), np.log(0.008), np.float32), opacity_logits=np.full(n, 2.0, np.float32),
        sh=sh)


def floor_gaussians(n=200, seed=9) -> GaussianSplatData:
    rng = np.random.default_rng(seed)
    means = np.concatenate([rng.uniform(-0.5, 0.5, (n, 2)), np.zeros((n, 1))], 1)
    sh = np.zeros((n, 16, 3), np.float32)
    sh[:, 0] = 0.3
    return GaussianSplatData(means=means.astype(np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                             log_scales=np.log(np.tile(np.float32([0.04, 0.04, 0.002]), (n, 1))),
                             opacity_logits=np.full(n, 3.0, np.float32), sh=sh)


def cameras():
    K = intrinsics_matrix(60.0, 60.0, 32.0, 24.0)
    return [Camera(f"{i}.png", K, look_at(np.array(eye, float), np.array([0.1, 0.0, 0.04])), 64, 48)
            for i, eye in enumerate([(0.9, -0.6, 0.6), (-0.7, 0.5, 0.5)])]


def toy_env(tmp_path, background=True, view_dependence=0.0) -> Environment:
    model = mujoco.MjModel.from_xml_string(TOY)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    objects = []
    for k, (object_id, half) in enumerate([(1, HALF), (2, (0.03, 0.03, 0.04))]):
        body = model.body(f"object_{object_id}").id
        pose0 = np.eye(4)
        pose0[:3, :3] = data.xmat[body].reshape(3, 3)
        pose0[:3, 3] = data.xpos[body]
        objects.append((object_id, pose0, box_gaussians(half, 300, seed=k, view_dependence=view_dependence)))
    bg = floor_gaussians() if background else floor_gaussians(n=0)
    return Environment(tmp_path, model, bg, objects, cameras())


def test_rendering_after_a_rigid_motion_equals_rendering_the_moved_gaussians(tmp_path):
    env = toy_env(tmp_path)
    new_pose = np.eye(4)
    new_pose[:3, :3] = Rotation.from_rotvec([0.3, -0.5, 1.1]).as_matrix()
    new_pose[:3, 3] = [0.05, -0.08, 0.2]
    env.place(1, pose=new_pose)
    got = env.render(0)
    canonical = [o.to_kernel() for o in (box_gaussians(HALF, 300, 0), box_gaussians((0.03, 0.03, 0.04), 300, 1))]
    moved_1 = transform_gaussians(canonical[0], Sim3.from_matrix(jnp.asarray(new_pose, jnp.float32)))
    moved_2 = transform_gaussians(canonical[1], Sim3.from_matrix(jnp.asarray(env.objects[1].pose0, jnp.float32)))
    direct = render(concatenate([floor_gaussians().to_kernel(), moved_1, moved_2]), env.cameras[0])
    for field in ("rgb", "alpha", "depth"):
        np.testing.assert_allclose(getattr(got, field), getattr(direct, field), atol=IMAGE_TOL)
    assert float(jnp.mean(got.alpha)) > 0.05


def test_gaussians_follow_their_collision_body_through_a_rollout(tmp_path):
    env = toy_env(tmp_path)
    env.place(1, linear_velocity=[0.6, 0.2, 1.0], angular_velocity=[2.0, -3.0, 5.0])
    geom_centre0 = env.data.geom_xpos[env.model.body_geomadr[env.objects[0].body_id]].copy()
    gaussian_offset = None
    for _ in range(40):
        env.step(6)
        g = env.gaussians()
        rows = slice(g.num - env.object_gaussians.num, g.num)
        centroid = np.asarray(g.means[rows][env.objects[0].gaussians]).mean(0)
        body_centre = env.data.geom_xpos[env.model.body_geomadr[env.objects[0].body_id]]
        offset = centroid - body_centre
        gaussian_offset = offset if gaussian_offset is None else gaussian_offset
        # the Gaussians' centroid keeps its offset in the body frame: compare in world, tolerance 1 cm
        rot = env.data.xmat[env.objects[0].body_id].reshape(3, 3)
        assert np.linalg.norm(centroid - (body_centre + rot @ (rot.T @ offset))) < CENTROID_TOL
        canonical_centroid = np.asarray(box_gaussians(HALF, 300, 0).means).mean(0)
        expected = body_centre + rot @ canonical_centroid
        assert np.linalg.norm(centroid - expected) < CENTROID_TOL
    assert np.linalg.norm(body_centre - geom_centre0) > 0.1, "the throw moved the body"


def test_rotating_a_body_and_the_camera_together_gives_the_same_image(tmp_path):
    """With view-dependent SH the object only looks the same if its SH were rotated."""
    env = toy_env(tmp_path, background=False, view_dependence=0.4)
    far = np.eye(4)
    far[:3, 3] = [5.0, 5.0, 5.0]
    env.place(2, pose=far)  # only object 1 in view
    body = env.objects[0]
    yaw = Rotation.from_euler("z", 70, degrees=True).as_matrix()
    centre = body.pose0[:3, 3]
    turn = np.eye(4)
    turn[:3, :3], turn[:3, 3] = yaw, centre - yaw @ centre   # about the body's vertical axis
    cam = env.cameras[0]
    turned_cam = Camera(cam.name, cam.K, cam.world_to_camera @ np.linalg.inv(turn), cam.width, cam.height)
    before = env.render(cam)
    env.place(1, pose=turn @ body.pose0)
    after = env.render(turned_cam)
    assert float(jnp.mean(before.alpha)) > 0.02
    np.testing.assert_allclose(after.rgb, before.rgb, atol=IMAGE_TOL)
    np.testing.assert_allclose(after.alpha, before.alpha, atol=IMAGE_TOL)
    # the same turn with the SH coefficients left unrotated shows a different object
    g = env.gaussians()
    rows = slice(g.num - env.object_gaussians.num, g.num)
    turned = jax.tree.map(lambda x: x[rows][body.gaussians], g)
    canonical = box_gaussians(HALF, 300, 0, view_dependence=0.4).to_kernel()
    wrong = render(turned.replace(sh=canonical.sh), turned_cam)
    assert float(jnp.max(jnp.abs(wrong.rgb - before.rgb))) > 20 * IMAGE_TOL


def test_shoot_hits_the_object_under_the_pixel_and_moves_it(tmp_path):
    env = toy_env(tmp_path)
    cam = env.cameras[0]
    centre = env.objects[0].pose0[:3, 3]
    uv, _ = cam.project(centre[None])
    result = env.shoot(0, uv[0], speed=2.0)
    assert result["hit"] == 1
    _, direction = env.ray(0, uv[0])
    start = env.placements()[0][:3, 3].copy()
    env.step(60)
    moved = env.placements()[0][:3, 3] - start
    along = np.dot(moved[:2], direction[:2]) / np.linalg.norm(direction[:2])
    assert along > 0.03 and along > 0.9 * np.linalg.norm(moved[:2]), "pushed along the ray, horizontally"
    sky = env.shoot(0, (32.0, 0.5), speed=1.0)
    assert sky["hit"] is None


def test_pusher_moves_the_box(tmp_path):
    spec = mujoco.MjSpec.from_string(TOY)
    pusher = spec.worldbody.add_body(name="pusher", mocap=True, pos=[0, 0, -10])
    pusher.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.02, 0.05, 0.03])
    toy = toy_env(tmp_path)
    objects = [(o.id, o.pose0, box_gaussians(h, 300, k))
               for k, (o, h) in enumerate(zip(toy.objects, (HALF, (0.03, 0.03, 0.04))))]
    env = Environment(tmp_path, spec.compile(), floor_gaussians(), objects, cameras())
    x0 = env.placements()[0][0, 3]
    env.push(start=[-0.3, 0.0, 0.03], end=[0.0, 0.0, 0.03], seconds=0.6)
    env.step(120)
    assert env.placements()[0][0, 3] - x0 > 0.02


@pytest.mark.slow  # MJX compiles the box-plane model for ~1.5 min on a 2-core CPU
def test_batched_worlds_step_like_the_single_environment_and_render_in_one_call(tmp_path):
    from phirie_jax.interact.batched import BatchedEnvironment

    env = toy_env(tmp_path)
    batch = BatchedEnvironment(env, num_worlds=3)
    throws = np.zeros((3, env.model.nv))
    throws[1, 0:3] = [0.4, 0.0, 0.8]      # world 1: object 1 thrown
    throws[2, 6:9] = [-0.3, 0.2, 0.5]     # world 2: object 2 thrown
    batch.set_velocities(throws)
    batch.step(48)
    placements = np.asarray(batch.placements())
    for world in range(3):
        env.reset()
        env.data.qvel[:] = throws[world]
        env.step(48)
        np.testing.assert_allclose(placements[world], env.placements(), atol=2e-3)
    assert np.linalg.norm(placements[1, 0, :3, 3] - placements[0, 0, :3, 3]) > 0.02
    out = batch.render([0, 1])
    assert out.rgb.shape == (3, 2, 48, 64, 3)
    chunked = batch.render([0, 1], max_images=2)  # one world per call, the last call padded
    np.testing.assert_array_equal(np.asarray(chunked.rgb), np.asarray(out.rgb))
    for world in (0, 2):
        env.reset()
        env.data.qvel[:] = throws[world]
        env.step(48)
        single = env.render(1)
        # same poses up to the MJX/C difference above: images agree closely
        assert float(jnp.mean(jnp.abs(out.rgb[world, 1] - single.rgb))) < 0.01
