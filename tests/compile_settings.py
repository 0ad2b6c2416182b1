"""How the tests have MuJoCo Warp compile its CPU kernels: for compile time, not run time.

MuJoCo Warp's kernels are compiled for the CPU at a process's first Warp step. At LLVM -O0 with
LLVM's default inlining, a cold kernel cache (as in CI) compiles in about half the time it takes
at Warp's defaults (-O2, raised inlining thresholds), which buy run time the tests' few steps do
not use; the arithmetic is the same IEEE arithmetic (no fast-math either way). Every test
process that steps Warp applies this: the pytest workers (``conftest.py``) and the processes
tests start.

XLA's CPU backend is left at its defaults: at ``--xla_backend_optimization_level=0`` it compiled
the tests' programs faster (27–30 %) but miscompiled one (``kernels.chamfer.nearest_point``: a
one-hot row feeding both a sum and a product came out empty for 30 of 301 queries), and level 1
was no faster than the default.
"""

from __future__ import annotations


def compile_quickly() -> None:
    """Set Warp's CPU compile options for the tests; nothing when Warp is not installed."""
    try:
        import warp
    except ImportError:
        return
    warp.config.optimization_level = 0
    warp.config.cpu_compiler_flags = None
