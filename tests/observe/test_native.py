"""Native code in a child process: a crash becomes NativeLibraryError naming the signal, an
exception comes back as itself, a result (NumPy arrays included) comes back whole."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from phirie_jax.errors import NativeLibraryError, SceneInputError
from phirie_jax.native import run_isolated
from tests.processes import kill_quietly, running, wait_for

OVERHEAD_S = 5.0  # generous bound on one call's start-up on a loaded 2-core CPU (measured ~0.1 s warm)
GONE_WITHIN_S = 5.0  # a dead parent's child is gone this soon
ROOT = Path(__file__).resolve().parents[2]


def segfault():
    os.kill(os.getpid(), signal.SIGSEGV)


def abort():
    os.abort()


def exit_quietly():
    os._exit(3)


def double(x, *, offset=0.0):
    return {"y": 2 * x + offset}


def raise_value_error():
    raise ValueError("bad value in the child")


class TwoArgumentError(Exception):
    def __init__(self, a, b):
        super().__init__(f"{a} and {b}")  # args holds one string: unpickling calls it with one argument


def raise_unpicklable():
    raise TwoArgumentError(1, 2)


def raise_scene_input_error():
    raise SceneInputError("scene.ply", "x", "wrong")


def test_segfault_becomes_an_error_naming_library_and_signal():
    with pytest.raises(NativeLibraryError, match=r"Open3D VoxelBlockGrid fusion died with signal 11 \(SIGSEGV\)") as e:
        run_isolated("Open3D", segfault, description="VoxelBlockGrid fusion")
    assert e.value.signal == "SIGSEGV" and e.value.library == "Open3D"


def test_abort_and_silent_exit():
    with pytest.raises(NativeLibraryError, match=r"CoACD died with signal 6 \(SIGABRT\)"):
        run_isolated("CoACD", abort)
    with pytest.raises(NativeLibraryError, match="exited with code 3 without a result"):
        run_isolated("X", exit_quietly)


def test_result_and_exceptions_come_back():
    x = np.arange(1_000_000, dtype=np.float32)
    t0 = time.perf_counter()
    out = run_isolated("numpy", double, x, offset=1.0)
    assert time.perf_counter() - t0 < OVERHEAD_S
    np.testing.assert_array_equal(out["y"], 2 * x + 1)
    with pytest.raises(ValueError, match="bad value in the child"):
        run_isolated("numpy", raise_value_error)
    with pytest.raises(RuntimeError, match="TwoArgumentError: 1 and 2"):
        run_isolated("numpy", raise_unpicklable)
    with pytest.raises(SceneInputError, match="scene.ply: x: wrong"):
        run_isolated("numpy", raise_scene_input_error)


def sleep_and_report(pid_file: str) -> None:
    """(In the child.) Record this process's id, then work far longer than the test."""
    Path(pid_file).write_text(str(os.getpid()))
    time.sleep(120)


PARENT = """
import sys
from phirie_jax.native import run_isolated
from tests.processes import kill_quietly, running, wait_for
from tests.observe.test_native import sleep_and_report
run_isolated("Open3D", sleep_and_report, sys.argv[1])
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl(PR_SET_PDEATHSIG) is Linux's")
def test_the_child_dies_with_a_killed_parent(tmp_path):
    pid_file = tmp_path / "child.pid"
    parent = subprocess.Popen([sys.executable, "-c", PARENT, str(pid_file)], cwd=ROOT)
    assert wait_for(lambda: pid_file.is_file() and pid_file.read_text(), 60), "the child did not start"
    child = int(pid_file.read_text())
    try:
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
        assert wait_for(lambda: not running(child), GONE_WITHIN_S), "the child outlived its killed parent"
    finally:
        kill_quietly(child)
