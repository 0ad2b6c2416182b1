"""``import kernels`` needs only jax and numpy (a GPU benchmark machine may have nothing else)."""

from __future__ import annotations

import pkgutil

import kernels
from tests.blocked_imports import run_without

BLOCKED = ("open3d", "trimesh", "mujoco", "coacd", "cv2", "scipy", "optax", "phirie_jax", "tyro", "rich")


def test_every_kernel_module_imports_with_only_jax_and_numpy():
    modules = [m.name for m in pkgutil.iter_modules(kernels.__path__, "kernels.")]
    assert "kernels.gaussians" in modules and "kernels.sh" in modules
    done = run_without(BLOCKED, modules)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr
