"""Shared fixtures: float64 switch, the real-data folder; XLA's and Warp's compile options for
the tests."""

from __future__ import annotations

from pathlib import Path

from tests.compile_settings import compile_quickly, compile_xla_quickly, xla_flag_outcome

compile_xla_quickly()  # before JAX starts: compile time over run time (tests/compile_settings.py)

import jax
import pytest

TESTS = Path(__file__).resolve().parent
SHARED_DATA = TESTS.parents[1] / "shared" / "data"

# The test files that take longest on a 2-core machine (each a minute or more of compiling and
# converting), run first: with ``--dist loadfile`` pytest-xdist hands out whole files in collection
# order, so a long file left for the end keeps one worker busy while the other has nothing to do.
LONGEST_FIRST = ("cluster/test_convert_many.py", "capture/test_command.py", "view/test_browser.py",
                 "interact/test_batched_warp.py", "test_pipeline.py", "interact/test_world_renderer.py",
                 "kernels/test_raster_merge.py", "capture/test_train.py", "test_output_folder.py",
                 "construct/background/test_stage.py", "kernels/test_composite_pallas.py")

compile_quickly()  # Warp's CPU kernels: compile time over run time (tests/compile_settings.py)


def pytest_report_header(config):
    return xla_flag_outcome()


def pytest_collection_modifyitems(config, items):
    """The files of ``LONGEST_FIRST`` first, in that order; the others after them, as collected
    (a stable sort: the tests of a file keep their order; items outside this folder come last)."""
    rank = {name: k for k, name in enumerate(LONGEST_FIRST)}

    def place(item) -> int:
        path = Path(item.path).resolve()
        return rank.get(path.relative_to(TESTS).as_posix(), len(rank)) if path.is_relative_to(TESTS) else len(rank)

    items.sort(key=place)


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
