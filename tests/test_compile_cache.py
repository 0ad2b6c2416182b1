"""The command line's persistent compilation cache (``phirie_jax.compile_cache``)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from phirie_jax import compile_cache

SETTINGS = ("JAX_COMPILATION_CACHE_DIR", "JAX_COMPILATION_CACHE_MAX_SIZE", "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS",
            "PHIRIE_COMPILE_CACHE")

# One program, jitted and run; prints the cache hits this process saw.
PROGRAM = """
import jax, jax.numpy as jnp
from jax._src import monitoring
from phirie_jax.compile_cache import use_compile_cache
hits = []
monitoring.register_event_listener(lambda event, **kw: hits.append(event) if event.endswith("cache_hits") else None)
print("folder", use_compile_cache())
x = jnp.arange(64.0).reshape(8, 8)
jax.jit(lambda a: jnp.tanh(a @ a.T).sum(0))(x).block_until_ready()
print("hits", len(hits))
"""


@pytest.fixture
def clean_env(monkeypatch, tmp_path):
    """No cache setting in the environment; XDG_CACHE_HOME under tmp_path."""
    for name in SETTINGS:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    return monkeypatch


def test_default_folder_is_the_users_cache(clean_env, tmp_path):
    folder = compile_cache.use_compile_cache()
    assert folder == tmp_path / "xdg" / "phirie_jax" / "xla"
    assert os.environ["JAX_COMPILATION_CACHE_DIR"] == str(folder)
    assert int(os.environ["JAX_COMPILATION_CACHE_MAX_SIZE"]) == compile_cache.MAX_BYTES


@pytest.mark.parametrize("value", ["off", "0", "No", "false"])
def test_turned_off(clean_env, value):
    clean_env.setenv("PHIRIE_COMPILE_CACHE", value)
    assert compile_cache.use_compile_cache() is None
    assert "JAX_COMPILATION_CACHE_DIR" not in os.environ


def test_jax_setting_wins(clean_env, tmp_path):
    clean_env.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "theirs"))
    clean_env.setenv("PHIRIE_COMPILE_CACHE", str(tmp_path / "ours"))
    assert compile_cache.use_compile_cache() == tmp_path / "theirs"
    assert os.environ["JAX_COMPILATION_CACHE_DIR"] == str(tmp_path / "theirs")


def test_a_second_process_reads_the_program(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in SETTINGS}
    env.update(PHIRIE_COMPILE_CACHE=str(tmp_path / "cache"), JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
               JAX_PLATFORMS="cpu")
    root = Path(__file__).resolve().parents[1]
    runs = [subprocess.run([sys.executable, "-c", PROGRAM], env=env, cwd=root, capture_output=True, text=True,
                           timeout=120) for _ in range(2)]
    for run in runs:
        assert run.returncode == 0, run.stderr[-2000:]
    first, second = (dict(line.split(" ", 1) for line in run.stdout.splitlines()) for run in runs)
    assert first["folder"] == second["folder"] == str(tmp_path / "cache")
    assert first["hits"] == "0" and int(second["hits"]) >= 1  # every program of the first run, read back
    assert any((tmp_path / "cache").iterdir())
