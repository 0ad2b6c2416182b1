"""Batches spread over four devices give the single-device results (issue 29).

Run by ``tests/test_multi_device.py`` in a process of its own with four forced host devices
(``XLA_FLAGS=--xla_force_host_platform_device_count=4``: the flag must be set before JAX starts)
and Eigen's single-threaded contractions (``--xla_cpu_multi_thread_eigen=false``: with several
threads a CPU contraction may split its sum by the threads a device gets, so the last bit of a
sum would depend on the device count, not on the sharding). Skipped when fewer devices are seen.

Each test runs the same program on one device and on four and compares per-row results. Where a
device runs as many rows as the single-device run, they are equal bit for bit. Where the
single-device run vmaps more rows together, XLA:CPU may vectorise a row's sums another way:
then discrete outcomes (verdicts, chosen hypotheses) are equal and values agree to float32
rounding (the tolerances below); the sphere worlds and the images come out bit for bit anyway.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from kernels.sharding import BatchMesh, map_rows

pytestmark = pytest.mark.skipif(jax.device_count() < 4, reason="needs four devices (tests/test_multi_device.py)")

ENERGY_TOL = 1e-6       # m: float32 sums of clipped distances over a few hundred points
ROTATION_TOL = 1e-5     # matrix entries after 20 ICP iterations in float32
TRANSLATION_TOL = 1e-6  # m
QPOS_TOL = 1e-4         # m / quaternion units: 120 float32 contact steps, 8 rows vmapped against 2
                        # (a toppling candidate grows a last-bit difference to ~2e-6 here)


def test_rows_are_padded_spread_over_the_devices_and_cut():
    mesh = BatchMesh.over()
    assert mesh.size == 4 and mesh.padded(10) == 12 and mesh.padded(8) == 8
    rows = mesh.put_rows(np.arange(8.0))
    assert {s.device for s in rows.addressable_shards} == set(jax.devices())
    assert all(s.data.shape == (2,) for s in rows.addressable_shards)

    @jax.jit
    def f(shared, xs):
        return map_rows(lambda s, x: (x * s, jnp.sum(x)), shared, xs, 2, mesh)

    xs = jnp.arange(30.0).reshape(10, 3)
    scaled, sums = f(jnp.float32(2.0), xs)
    assert scaled.shape == (10, 3) and sums.shape == (10,)   # the pad (2 rows) is cut
    np.testing.assert_array_equal(scaled, 2.0 * xs)
    np.testing.assert_array_equal(sums, xs.sum(1))


def test_registration_search_over_devices_picks_the_same_hypotheses():
    from phirie_jax.construct.objects import register as reg
    from tests.construct.objects.test_register import SMALL, l_mesh
    from tests.kernels.shapes import l_shape, partial_view

    rng = np.random.default_rng(1)
    points, normals = l_shape(6000, rng)
    obs = reg.prepare_observation(partial_view(points, normals, 700, rng), 0.0, True, SMALL)
    model = reg.sample_model(*l_mesh(1.0), SMALL.points, 0)
    # 13 yaws: 234 hypotheses, padded to 236 on four devices; 3 refined, padded to 4
    config = dataclasses.replace(SMALL, search=dataclasses.replace(SMALL.search, num_yaws=13))
    one_best, one = reg.search(model, obs, config, reg.ALL_AXES, devices=1)
    best, out = reg.search(model, obs, config, reg.ALL_AXES, devices=4)
    assert [h.axis for h in best] == [h.axis for h in one_best]
    np.testing.assert_array_equal(out.axis, one.axis)
    np.testing.assert_array_equal(out.yaw, one.yaw)
    np.testing.assert_allclose(out.sweep_energy, one.sweep_energy, rtol=0, atol=ENERGY_TOL)
    np.testing.assert_allclose(out.energy, one.energy, rtol=0, atol=ENERGY_TOL)
    np.testing.assert_allclose(out.rotation, one.rotation, rtol=0, atol=ROTATION_TOL)
    np.testing.assert_allclose(out.translation, one.translation, rtol=0, atol=TRANSLATION_TOL)
    np.testing.assert_array_equal(out.support, one.support)


def test_mjx_drop_tests_over_devices_equal_one_device():
    from phirie_jax.construct.physics import mjx_batch
    from phirie_jax.construct.physics.collision import hull_part
    from phirie_jax.construct.physics.config import DropTestConfig
    from phirie_jax.construct.physics.droptest import body_from_parts, bucket_template, build_model, spawn_qpos, verdict
    from tests.fixtures import droptest_cases as cases

    config = dataclasses.replace(DropTestConfig(), settle_time=0.25, free_time=0.25, min_batch=2)
    chosen = cases.case_set(7, seed=11)               # 8 rows: 2 a device on four
    bodies = [body_from_parts((hull_part(c.vertices),), c.pose) for c in chosen]
    models = [build_model(b, 1, config) for b in bodies]
    qpos0 = np.stack([spawn_qpos(b) for b in bodies])
    template_model, template = bucket_template(1, config)
    assert mjx_batch.padded_count(7, config, BatchMesh.over(3)) == 9   # 8, then a multiple of 3
    settled, final = mjx_batch.run(template_model, template, models, qpos0, config, devices=4)
    # a device's rows are simulated exactly as one device simulates as many rows
    first = mjx_batch.run(template_model, template, models[:2], qpos0[:2], config, devices=1)
    np.testing.assert_array_equal(settled[:2], first[0])
    np.testing.assert_array_equal(final[:2], first[1])
    # all seven on one device (8 rows vmapped together): the same up to float32 rounding
    one = mjx_batch.run(template_model, template, models, qpos0, config, devices=1)
    np.testing.assert_allclose(settled, one[0], rtol=0, atol=QPOS_TOL)
    np.testing.assert_allclose(final, one[1], rtol=0, atol=QPOS_TOL)
    verdicts = [verdict(m, q, s, f, config, "mjx").stable for m, q, s, f in zip(models, qpos0, *one)]
    assert verdicts == [verdict(m, q, s, f, config, "mjx").stable
                        for m, q, s, f in zip(models, qpos0, settled, final)]
    # the candidates moved: a comparison of untouched states would prove nothing
    assert np.abs(final[:, :3] - qpos0[:, :3]).max() > 1e-3


SPHERES = f"""
<mujoco>
  <option timestep="{1 / 240}"/>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 0.1" friction="0.6"/>
    <body name="object_1" pos="0 0 0.05"><freejoint/><geom type="sphere" size="0.05" mass="0.3"/></body>
    <body name="object_2" pos="0.15 0.05 0.04"><freejoint/><geom type="sphere" size="0.04" mass="0.2"/></body>
  </worldbody>
</mujoco>"""


def _sphere_env(tmp_path):
    from phirie_jax.interact.environment import Environment
    from tests.interact.test_environment import box_gaussians, cameras, floor_gaussians

    model = mujoco.MjModel.from_xml_string(SPHERES)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    objects = []
    for k, (object_id, radius) in enumerate(((1, 0.05), (2, 0.04))):
        body = model.body(f"object_{object_id}").id
        pose0 = np.eye(4)
        pose0[:3, 3] = data.xpos[body]
        objects.append((object_id, pose0, box_gaussians((radius,) * 3, 150, seed=k)))
    return Environment(tmp_path, model, floor_gaussians(n=100), objects, cameras())


def test_batched_worlds_over_devices_step_and_render_as_on_one_device(tmp_path):
    from phirie_jax.interact.batched import BatchedEnvironment, _advance

    env = _sphere_env(tmp_path)
    worlds = 6                                  # padded to 8 worlds on four devices
    throws = np.random.default_rng(3).normal(0.0, 0.6, (worlds, env.model.nv))
    runs = {}
    for devices in (1, 4):
        batch = BatchedEnvironment(env, worlds, devices=devices)
        assert batch.padded_worlds == (6 if devices == 1 else 8) and batch.data.qpos.shape[0] == worlds
        batch.set_velocities(throws)
        batch.step(12)
        compiled = _advance._cache_size()
        batch.step(12)          # fed its own state (empty row blocks too): no second compile
        assert _advance._cache_size() == compiled
        runs[devices] = (jax.device_get(batch.data), np.asarray(batch.placements()),
                         batch.render([0, 1], max_images=4))   # 2 worlds a device and call
    (data1, place1, image1), (data4, place4, image4) = runs[1], runs[4]
    for name in ("qpos", "qvel", "xpos", "xquat"):
        np.testing.assert_array_equal(getattr(data4, name), getattr(data1, name), err_msg=name)
    np.testing.assert_array_equal(place4, place1)
    assert image4.rgb.shape == (worlds, 2, 48, 64, 3)
    for name in ("rgb", "depth", "alpha"):
        np.testing.assert_array_equal(getattr(image4, name), getattr(image1, name), err_msg=name)
    # the throws made the worlds differ, and the pad worlds are nowhere in the results
    assert np.abs(place1[1] - place1[0]).max() > 1e-3
