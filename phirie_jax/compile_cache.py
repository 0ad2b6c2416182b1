"""The persistent XLA compilation cache of the command line: programs compiled once are read
back by later runs instead of compiled again.

A step of 3DGS training or a conversion's kernels take seconds each to compile (XLA, and Triton
for the Pallas kernels on a GPU), every run, for the same shapes. JAX can keep the compiled
executables on disk, keyed by the program, the compile options, the backend and the JAX
version, so a change to any of them compiles afresh. ``phirie`` turns it on for its commands,
in ``$XDG_CACHE_HOME/phirie_jax/xla`` (``~/.cache/...`` by default), at most
``MAX_BYTES`` with the least recently used entries evicted. The environment decides first:

- ``JAX_COMPILATION_CACHE_DIR`` set: JAX's own setting, used as it is;
- ``PHIRIE_COMPILE_CACHE=off`` (or 0, no, false): no cache; any other value: the folder to use.

It is set in the environment before JAX reads it, so processes the command starts (Ray workers,
conversions) share it, and in JAX's configuration when JAX is already imported.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

MAX_BYTES = 4 << 30        # the cache's size limit (least recently used entries go first)
MIN_COMPILE_SECONDS = 0.5  # programs compiled faster than this are not written (JAX's default: 1 s)
OFF = ("off", "0", "no", "false")


def default_cache_folder() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "phirie_jax" / "xla"


def use_compile_cache() -> Path | None:
    """Turn the persistent compilation cache on (module docstring); returns its folder, or None
    when it is off."""
    if "JAX_COMPILATION_CACHE_DIR" in os.environ:
        return Path(os.environ["JAX_COMPILATION_CACHE_DIR"]) if os.environ["JAX_COMPILATION_CACHE_DIR"] else None
    choice = os.environ.get("PHIRIE_COMPILE_CACHE", "")
    if choice.lower() in OFF:
        return None
    folder = Path(choice) if choice else default_cache_folder()
    settings = {"JAX_COMPILATION_CACHE_DIR": str(folder), "JAX_COMPILATION_CACHE_MAX_SIZE": str(MAX_BYTES),
                "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": str(MIN_COMPILE_SECONDS)}
    for name, value in settings.items():
        os.environ.setdefault(name, value)
    if "jax" in sys.modules:  # already imported: it has read the environment
        import jax

        jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
        jax.config.update("jax_compilation_cache_max_size", int(os.environ["JAX_COMPILATION_CACHE_MAX_SIZE"]))
        jax.config.update("jax_persistent_cache_min_compile_time_secs",
                          float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]))
    return folder
