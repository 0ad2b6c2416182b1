"""``import kernels`` needs only jax and numpy (a GPU benchmark machine may have nothing else)."""

from __future__ import annotations

import pkgutil
import subprocess
import sys
from pathlib import Path

import kernels

BLOCKED = ("open3d", "trimesh", "mujoco", "coacd", "cv2", "scipy", "optax", "phirie_jax", "tyro", "rich")


def test_every_kernel_module_imports_with_only_jax_and_numpy():
    modules = [m.name for m in pkgutil.iter_modules(kernels.__path__, "kernels.")]
    assert "kernels.gaussians" in modules and "kernels.sh" in modules
    script = f"""
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {BLOCKED!r}:
            raise ImportError("blocked in this test: " + name)
sys.meta_path.insert(0, Block())
for name in {modules!r}:
    __import__(name)
print("ok")
"""
    root = Path(kernels.__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, "-c", script], cwd=root, capture_output=True, text=True)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr
