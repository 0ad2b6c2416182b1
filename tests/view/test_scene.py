"""The viewer's arrays and poses against slow references and by their properties."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kernels.gaussians import Gaussians
from phirie_jax.geometry import sim3_matrix
from phirie_jax.io.camera import intrinsics_matrix
from phirie_jax.synthetic.scene import look_at
from phirie_jax.types import Camera
from phirie_jax.view.scene import camera_view, node_motion, placed_vertices, screen_position, splat_arrays

SH_C0 = 0.28209479177387814
FLOAT32_TOL = 1e-5     # float32 arrays against float64 references
PIXEL_TOL = 1e-6       # normalized screen coordinates: exact formulas, float64


def random_gaussians(n: int, seed: int, degree: int = 2) -> Gaussians:
    rng = np.random.default_rng(seed)
    return Gaussians(means=jnp.asarray(rng.normal(size=(n, 3)), jnp.float32),
                     quats=jnp.asarray(rng.normal(size=(n, 4)), jnp.float32),
                     log_scales=jnp.asarray(rng.uniform(-5, -2, (n, 3)), jnp.float32),
                     opacity_logits=jnp.asarray(rng.normal(size=n) * 3, jnp.float32),
                     sh=jnp.asarray(rng.normal(size=(n, (degree + 1) ** 2, 3)) * 2, jnp.float32))


def test_splat_arrays_match_a_per_gaussian_reference():
    g = random_gaussians(50, seed=1)
    arrays = splat_arrays(g)
    for i in range(g.num):
        q = np.asarray(g.quats[i], np.float64)
        rot = Rotation.from_quat(q / np.linalg.norm(q), scalar_first=True).as_matrix()
        scales = np.exp(np.asarray(g.log_scales[i], np.float64))
        cov = rot @ np.diag(scales**2) @ rot.T
        assert np.allclose(arrays.covariances[i], cov, rtol=1e-4, atol=FLOAT32_TOL * np.abs(cov).max())
        rgb = np.clip(0.5 + SH_C0 * np.asarray(g.sh[i, 0], np.float64), 0.0, 1.0)  # degree 0 only
        assert np.allclose(arrays.rgbs[i], rgb, atol=FLOAT32_TOL)
        opacity = 1.0 / (1.0 + np.exp(-float(g.opacity_logits[i])))
        assert arrays.opacities[i, 0] == pytest.approx(opacity, abs=FLOAT32_TOL)
    assert np.array_equal(arrays.centers, np.asarray(g.means))
    assert arrays.rgbs.min() >= 0.0 and arrays.rgbs.max() <= 1.0
    assert arrays.opacities.shape == (50, 1) and arrays.covariances.dtype == np.float32


def test_node_motion_carries_the_t0_placement_to_the_current_one():
    rng = np.random.default_rng(2)
    canonical = rng.normal(size=(20, 3))
    s0 = sim3_matrix(1.7, Rotation.random(random_state=3).as_matrix(), rng.normal(size=3))
    rigid = sim3_matrix(1.0, Rotation.random(random_state=4).as_matrix(), rng.normal(size=3))
    st = rigid @ s0   # S(t) = T(t) T(0)⁻¹ S(0)
    wxyz, position = node_motion(st, s0)
    moved = Rotation.from_quat(wxyz, scalar_first=True).apply(placed_vertices(canonical, s0)) + position
    assert np.allclose(moved, placed_vertices(canonical, st), atol=1e-9)
    identity_wxyz, zero = node_motion(s0, s0)
    assert np.allclose(np.abs(identity_wxyz), [1, 0, 0, 0]) and np.allclose(zero, 0)
    with pytest.raises(ValueError, match="rigid"):
        node_motion(sim3_matrix(1.1, np.eye(3), np.zeros(3)) @ s0, s0)


def test_screen_position_agrees_with_the_camera_projection():
    width, height = 160, 120
    camera = Camera("a.png", intrinsics_matrix(140.0, 140.0, width / 2, height / 2),
                    look_at(np.array([0.6, -0.4, 0.5]), np.array([0.0, 0.0, 0.1])), width, height)
    view = camera_view(camera)
    assert view.aspect == pytest.approx(width / height)
    points = np.random.default_rng(5).uniform(-0.2, 0.2, (30, 3))
    pixels, depth = camera.project(points)
    for point, pixel in zip(points, pixels):
        u, v = screen_position(point, view)
        assert u == pytest.approx(pixel[0] / width, abs=PIXEL_TOL)
        assert v == pytest.approx(pixel[1] / height, abs=PIXEL_TOL)
    behind = camera.center + (camera.center - np.array([0.0, 0.0, 0.1]))
    assert screen_position(behind, view) is None
    assert np.allclose(view.look_at(1.0) - view.position, camera.camera_to_world[:3, 2])
