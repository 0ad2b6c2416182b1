"""How the tests have XLA and MuJoCo Warp compile for the CPU: for compile time, not run time.

Most of a test's time is compiling: the tests run each program a few times on tiny inputs.

XLA: the tests compile with XLA's CPU loop emitters instead of its MLIR fusion emitters
(``--xla_cpu_use_fusion_emitters=false``), set in the environment before JAX starts, so the
pytest workers and every process a test starts use it. Measured on this project's 2-core CPU:
the rasterizer tests compiled in 45 % less time (37.2 → 20.3 s, two tests), the whole default
suite took 18 % less CPU time (29.5 → 24.0 min), and every test passed. Both emitters implement
the same HLO; the project's own commands keep XLA's defaults. A JAX whose XLA lacks the flag
would stop at start-up, so it is first tried in a small process (once per test session: the
answer is kept in the environment for the workers) and left out when refused. Other settings
measured and not taken: ``--xla_backend_optimization_level=0`` compiled 27–30 % faster but
miscompiled one program (``kernels.chamfer.nearest_point``: a one-hot row feeding both a sum and
a product came out empty for 30 of 301 queries); level 1 was no faster than the default; LLVM's
expensive passes off (``--xla_llvm_disable_expensive_passes``) saved 9 %, within the noise.

MuJoCo Warp's kernels are compiled for the CPU at a process's first Warp step. At LLVM -O0 with
LLVM's default inlining, a cold kernel cache (as in CI) compiles in about half the time it takes
at Warp's defaults (-O2, raised inlining thresholds), which buy run time the tests' few steps do
not use; the arithmetic is the same IEEE arithmetic (no fast-math either way). Every test
process that steps Warp applies this: the pytest workers (``conftest.py``) and the processes
tests start.
"""

from __future__ import annotations

import os
import subprocess
import sys

XLA_CPU_FLAG = "--xla_cpu_use_fusion_emitters=false"
PROBE_RESULT_ENV = "PHIRIE_TESTS_XLA_CPU_FLAG"  # "taken" or "refused" once tried in this session
TRY_SECONDS = 120


def compile_xla_quickly() -> None:
    """Add ``XLA_CPU_FLAG`` to ``XLA_FLAGS`` when this JAX's XLA accepts it (module docstring).
    Call before JAX's first computation: XLA reads its flags when its backend starts."""
    flags = os.environ.get("XLA_FLAGS", "")
    if XLA_CPU_FLAG.split("=")[0] in flags:
        return
    with_flag = f"{flags} {XLA_CPU_FLAG}".strip()
    if PROBE_RESULT_ENV not in os.environ:
        probe = [sys.executable, "-c", "import jax.numpy as jnp; jnp.zeros(2).sum().block_until_ready()"]
        try:
            accepted = subprocess.run(probe, env={**os.environ, "XLA_FLAGS": with_flag, "JAX_PLATFORMS": "cpu"},
                                      capture_output=True, timeout=TRY_SECONDS, check=False).returncode == 0
        except subprocess.TimeoutExpired:
            accepted = False
        os.environ[PROBE_RESULT_ENV] = "taken" if accepted else "refused"
    if os.environ[PROBE_RESULT_ENV] == "taken":
        os.environ["XLA_FLAGS"] = with_flag


def xla_flag_outcome() -> str:
    """One line on what ``compile_xla_quickly`` decided, for the test run's header."""
    outcome = os.environ.get(PROBE_RESULT_ENV)
    if outcome is None:
        return f"XLA_FLAGS as given ({os.environ.get('XLA_FLAGS', '')!r}): not tried"
    if outcome == "refused":
        return f"XLA refused {XLA_CPU_FLAG} (or did not start in {TRY_SECONDS} s): XLA's default CPU emitters"
    return f"XLA_FLAGS: {os.environ.get('XLA_FLAGS', '')}"


def compile_quickly() -> None:
    """Set Warp's CPU compile options for the tests; nothing when Warp is not installed."""
    try:
        import warp
    except ImportError:
        return
    warp.config.optimization_level = 0
    warp.config.cpu_compiler_flags = None
