"""How many XLA programs a block of host code compiled, and how long that took.

A program compiles once per distinct shape: host code that hands JAX arrays of a new size to an
eager operation (a ``jnp.concatenate``, a slice) compiles a new small program each time, which on
a GPU costs tens of milliseconds apiece. Stages record the count beside their timings, so a
regression shows as a count that grows with the scene.

    with CompileCount() as compiles:
        ...
    compiles.count, compiles.seconds
"""

from __future__ import annotations

import threading
from typing import Self

BACKEND_COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"  # jax._src.dispatch's event name

_active: list[CompileCount] = []
_lock = threading.Lock()
_registered = False


def _listener(event: str, duration: float, **_kwargs) -> None:
    if event != BACKEND_COMPILE_EVENT:
        return
    with _lock:
        for counter in _active:
            counter.count += 1
            counter.seconds += duration


class CompileCount:
    """Counts the backend compilations (and their seconds) while its ``with`` block runs, in any thread."""

    def __init__(self):
        self.count = 0
        self.seconds = 0.0

    def __enter__(self) -> Self:
        global _registered
        import jax

        with _lock:
            if not _registered:
                jax.monitoring.register_event_duration_secs_listener(_listener)
                _registered = True
            _active.append(self)
        return self

    def __exit__(self, *exc) -> None:
        with _lock:
            _active.remove(self)

    def record(self) -> dict:
        return {"count": self.count, "seconds": round(self.seconds, 3)}
