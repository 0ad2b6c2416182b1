"""The drop-test and environment benchmarks' modules import with only jax, mujoco(-mjx), numpy and scipy
(a lent GPU machine may have nothing else). trimesh is not blocked: mujoco-mjx itself imports
it (a dependency of that package), but our modules must not need it."""

from __future__ import annotations

from tests.blocked_imports import run_without

BLOCKED = ("open3d", "coacd", "cv2", "optax", "tyro", "rich", "pybullet", "shapely", "rtree")
MODULES = ("phirie_jax.construct.physics.droptest", "phirie_jax.construct.physics.mjx_batch",
           "phirie_jax.construct.physics.collision", "phirie_jax.construct.physics.priors",
           "phirie_jax.construct.physics.config", "tests.fixtures.droptest_cases",
           "phirie_jax.interact.environment", "phirie_jax.interact.batched", "phirie_jax.interact.mjx_model")


def test_benchmark_modules_import_without_the_mesh_stack():
    done = run_without(BLOCKED, MODULES, then="""
import runpy
for script in ("bench_droptest", "droptest_tuning"):
    sys.argv = [script, "--help"]
    try:
        runpy.run_module(f"experiments.{script}", run_name="__main__")
    except SystemExit as e:
        assert e.code == 0, (script, e.code)
""")
    assert done.returncode == 0 and done.stdout.strip().endswith("ok"), done.stderr[-2000:]
