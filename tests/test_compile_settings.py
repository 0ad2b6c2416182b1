"""The tests' XLA flag is tried in a small process first: a flag this JAX's XLA refuses (it would
stop every process at start-up) is left out of ``XLA_FLAGS``; the longest test files are listed
by names that exist."""

from __future__ import annotations

import os
import subprocess

import pytest

from tests import compile_settings
from tests.conftest import LONGEST_FIRST, TESTS


def _probe_exiting(code: int, calls: list):
    def run(command, env, **kwargs):
        calls.append(env["XLA_FLAGS"])
        return subprocess.CompletedProcess(command, code)
    return run


@pytest.mark.parametrize("exit_code, outcome", [(0, "taken"), (1, "refused")])
def test_the_flag_is_added_only_when_the_trial_process_starts(monkeypatch, exit_code, outcome):
    calls = []
    monkeypatch.setattr(compile_settings.subprocess, "run", _probe_exiting(exit_code, calls))
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=1")
    monkeypatch.delenv(compile_settings.PROBE_RESULT_ENV, raising=False)
    compile_settings.compile_xla_quickly()
    compile_settings.compile_xla_quickly()  # tried once: the answer is kept for the workers
    with_flag = f"--xla_force_host_platform_device_count=1 {compile_settings.XLA_CPU_FLAG}"
    assert calls == [with_flag]                     # the trial ran with the user's flags and this one
    assert os.environ[compile_settings.PROBE_RESULT_ENV] == outcome
    assert os.environ["XLA_FLAGS"] == (with_flag if outcome == "taken" else "--xla_force_host_platform_device_count=1")
    assert ("refused" in compile_settings.xla_flag_outcome()) == (outcome == "refused")  # the run's header says


def test_a_flag_already_given_is_left_as_it_is(monkeypatch):
    monkeypatch.setattr(compile_settings.subprocess, "run", _probe_exiting(0, calls := []))
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=true")
    compile_settings.compile_xla_quickly()
    assert calls == [] and os.environ["XLA_FLAGS"] == "--xla_cpu_use_fusion_emitters=true"


def test_the_longest_files_are_test_files_of_this_folder():
    assert all((TESTS / name).is_file() for name in LONGEST_FIRST)
