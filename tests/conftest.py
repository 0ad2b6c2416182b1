"""Shared fixtures: float64 switch, the real-data folder; XLA's and Warp's compile options for
the tests."""

from __future__ import annotations

from pathlib import Path

from tests.compile_settings import compile_quickly, compile_xla_quickly

compile_xla_quickly()  # before JAX starts: compile time over run time (tests/compile_settings.py)

import jax  # noqa: E402
import pytest  # noqa: E402

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

compile_quickly()  # Warp's CPU kernels: compile time over run time (tests/compile_settings.py)


@pytest.fixture
def x64():
    """Run one test with 64-bit JAX arrays, then restore the previous setting."""
    previous = jax.config.read("jax_enable_x64")
    jax.config.update("jax_enable_x64", True)
    try:
        yield
    finally:
        jax.config.update("jax_enable_x64", previous)


def shared_data(*parts: str) -> Path:
    """Path under ../shared/data; skips the calling test when it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real data not present: {path}")
    return path
