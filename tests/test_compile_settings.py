"""The tests' XLA flag is tried in a small process first: a flag this JAX's XLA refuses (it would
stop every process at start-up) is left out of ``XLA_FLAGS``."""

from __future__ import annotations

from tests import compile_settings


def test_a_flag_xla_refuses_is_left_out(monkeypatch):
    monkeypatch.setattr(compile_settings, "XLA_CPU_FLAG", "--xla_cpu_no_such_setting=false")
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=1")
    monkeypatch.delenv(compile_settings.TRIED, raising=False)
    compile_settings.compile_xla_quickly()
    assert compile_settings.os.environ[compile_settings.TRIED] == "refused"
    assert compile_settings.os.environ["XLA_FLAGS"] == "--xla_force_host_platform_device_count=1"


def test_a_flag_xla_takes_is_added_once(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=1")
    monkeypatch.delenv(compile_settings.TRIED, raising=False)
    compile_settings.compile_xla_quickly()
    compile_settings.compile_xla_quickly()
    assert compile_settings.os.environ[compile_settings.TRIED] == "taken"
    assert compile_settings.os.environ["XLA_FLAGS"] == \
        f"--xla_force_host_platform_device_count=1 {compile_settings.XLA_CPU_FLAG}"
