"""Batched worlds rendered with the background binned once per camera: each world's image is
the single environment's render of the same state."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from phirie_jax.interact.batched import WorldCapacities, WorldRenderer, as_pixels
from phirie_jax.render import quarter_octave
from tests.interact.test_environment import toy_env

IMAGE_TOL = 1e-5  # the same float32 arithmetic, compiled into different programs


def three_worlds(env, on_world=lambda: None) -> np.ndarray:
    """Placements (3, K, 4, 4) of the toy scene's objects in three worlds, turned at random and
    low enough that the floor's disks cut through the boxes: depths interleave. The tests below
    render these, so that they share compiled programs (one per capacities and world count).
    ``on_world()`` is called with each world's objects placed in ``env``."""
    rng = np.random.default_rng(4)
    placements = []
    for _ in range(3):
        for obj in env.objects:
            pose = np.eye(4)
            pose[:3, :3] = Rotation.from_rotvec(rng.normal(0.0, 0.8, 3)).as_matrix()
            pose[:3, 3] = [rng.uniform(-0.1, 0.25), rng.uniform(-0.1, 0.15), rng.uniform(0.0, 0.04)]
            env.place(obj.id, pose=pose)
        on_world()
        placements.append(env.placements())
    return np.stack(placements)


def test_each_world_renders_as_the_single_environment(tmp_path):
    env = toy_env(tmp_path, view_dependence=0.3)
    renderer = WorldRenderer(env)
    # far too small: the render must grow every capacity, dropping nothing
    renderer.capacities = WorldCapacities(moving=16, tiles=1, entries=1)
    singles = []
    placements = three_worlds(env, lambda: singles.append([env.render(c) for c in (0, 1)]))
    out = renderer.render(placements, [0, 1], max_images=4)  # 2 worlds a call
    assert out.rgb.shape == (3, 2, 48, 64, 3) and renderer.retries >= 1
    for world in range(3):
        for cam in range(2):
            single = singles[world][cam]
            for key in ("rgb", "depth", "alpha"):
                np.testing.assert_allclose(getattr(out, key)[world, cam], getattr(single, key),
                                           atol=IMAGE_TOL, err_msg=f"world {world} camera {cam} {key}")
    # the worlds differ, and the objects are in view
    assert float(np.abs(out.rgb[0, 0] - out.rgb[1, 0]).max()) > 0.1
    assert float(np.mean(out.alpha)) > 0.05
    # only some tiles were recomposited, and the capacities hold what the worlds used
    assert 1 < renderer.capacities.tiles < 12  # of the 4 × 3 tiles
    # sized by counting before the first render: the same images without a retry
    counted = WorldRenderer(env)
    again = counted.render(placements, [0, 1], max_images=4)
    np.testing.assert_allclose(again.rgb, out.rgb, atol=IMAGE_TOL)
    assert counted.retries == 0 and counted.capacities.tiles >= 1
    # the background's lists hold what its busiest camera needs, at most a fifth of them idle
    views, config, _ = next(iter(renderer._views.values()))
    assert config.capacity == quarter_octave(int(np.max(views.needed)))


def test_policy_pixels_are_the_render_in_the_policys_type(tmp_path):
    import jax.numpy as jnp
    import pytest

    env = toy_env(tmp_path, view_dependence=0.3)
    renderer = WorldRenderer(env)
    placements = three_worlds(env)
    full = renderer.render(placements, [0, 1], max_images=4)
    as_uint8 = renderer.render(placements, [0, 1], max_images=4, pixels="uint8")
    assert as_uint8.shape == full.rgb.shape == (3, 2, 48, 64, 3) and as_uint8.dtype == jnp.uint8
    expected = np.round(np.clip(np.asarray(full.rgb), 0.0, 1.0) * 255.0)
    # the same render compiled into another program: a value on a rounding edge may move by one
    assert np.abs(np.asarray(as_uint8, np.int32) - expected).max() <= 1
    assert np.mean(np.asarray(as_uint8) == expected) > 0.99
    as_bf16 = as_pixels(full.rgb, "bfloat16")          # the same conversion the program applies
    assert as_bf16.dtype == jnp.bfloat16
    np.testing.assert_allclose(np.asarray(as_bf16, np.float32), full.rgb, atol=2 ** -8 + IMAGE_TOL)
    assert len(as_uint8.devices()) >= 1                              # a device array, not a host copy
    with pytest.raises(ValueError, match="pixels: 'int8'"):
        renderer.render(placements, [0], pixels="int8")
