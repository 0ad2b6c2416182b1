"""Batches over several devices: ``tests/multi_device.py``, run with four forced host devices.

``--xla_force_host_platform_device_count`` only counts before JAX starts, and this process has
started it already, so each test of that module runs in a pytest process of its own (a fresh
JAX), which says whether it passed."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FLAGS = "--xla_force_host_platform_device_count=4 --xla_cpu_multi_thread_eigen=false"
TIMEOUT_S = 900

CASES = [
    "test_rows_are_padded_spread_over_the_devices_and_cut",
    "test_registration_search_over_devices_picks_the_same_hypotheses",
    # MJX compiles each of these programs for 30-50 s on a 2-core CPU, three and two of them
    pytest.param("test_mjx_drop_tests_over_devices_equal_one_device", marks=pytest.mark.slow),
    pytest.param("test_batched_worlds_over_devices_step_and_render_as_on_one_device", marks=pytest.mark.slow),
]


def run_on_four_devices(test: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} {FLAGS}".strip(), JAX_PLATFORMS="cpu")
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:xdist", "-p", "no:cacheprovider", "-m", "",
               f"tests/multi_device.py::{test}"]
    return subprocess.run(command, check=False, cwd=ROOT, env=env, capture_output=True, text=True, timeout=TIMEOUT_S)


@pytest.mark.parametrize("test", CASES)
def test_on_four_devices(test):
    done = run_on_four_devices(test)
    tail = (done.stdout + done.stderr)[-4000:]
    assert done.returncode == 0, tail
    assert "1 passed" in done.stdout and "skipped" not in done.stdout, tail
