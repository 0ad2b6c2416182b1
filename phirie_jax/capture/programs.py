"""The training's programs (the step per Gaussian rows and tile-intersection capacity, the
densification per bucket), compiled ahead of need on a background thread.

A training grows: densification moves the Gaussians to larger buckets and the tile
intersections outgrow the buffer, and each new size is a new program (a few seconds of XLA and
Triton compilation for a step, with the device idle). The loop sees both coming: the count
after a densification nears its bucket, a step's intersections near the capacity. It asks for
the programs of the next sizes then (``prepare``); a thread traces and compiles them from the
argument shapes while the device keeps training, and the call that first needs one finds it
ready. A program nobody prepared is compiled on the spot by its jit, as before.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import jax

Key = tuple  # what tells programs apart: a name and sizes, e.g. ("step", rows, capacity)


def with_rows(tree: Any, rows: int) -> Any:
    """Shapes (``jax.ShapeDtypeStruct``) of ``tree``'s leaves with their leading axis set to
    ``rows``; scalar leaves keep theirs (Adam's step count)."""
    def spec(x):
        shape = (rows,) + tuple(x.shape[1:]) if x.ndim else ()
        return jax.ShapeDtypeStruct(shape, x.dtype, weak_type=getattr(x, "weak_type", False))
    return jax.tree.map(spec, tree)


def like(tree: Any) -> Any:
    """Shapes of ``tree``'s leaves as they are."""
    return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, weak_type=getattr(x, "weak_type", False)),
                        tree)


class Programs:
    """Jitted functions' programs by key, from ``prepare``'s compilations where they are ready.
    Not ``enabled``: ``prepare`` does nothing (every program is compiled by its jit)."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.ready: dict[Key, Any] = {}
        self.pending: dict[Key, threading.Thread] = {}
        self.background_s = 0.0   # compilation time spent on the thread
        self.failed: list[str] = []
        self._lock = threading.Lock()

    def prepare(self, key: Key, fn: Callable, shapes: tuple, **statics) -> None:
        """Compile ``fn`` (a jitted function) for ``key`` on a thread: shapes, its positional
        arguments' shapes; statics, its static keyword arguments."""
        if not self.enabled:
            return
        with self._lock:
            if key in self.ready or key in self.pending:
                return

            def compile_it():
                t = time.perf_counter()
                try:
                    compiled = fn.lower(*shapes, **statics).compile()
                except Exception as err:  # noqa: BLE001 (the jit compiles it when it is needed)
                    with self._lock:
                        self.failed.append(f"{key}: {type(err).__name__}: {err}"[:300])
                        self.pending.pop(key, None)
                    return
                with self._lock:
                    self.ready[key] = compiled
                    self.pending.pop(key, None)
                    self.background_s += time.perf_counter() - t

            thread = threading.Thread(target=compile_it, name=f"compile {key}", daemon=True)
            self.pending[key] = thread
        thread.start()

    def __call__(self, key: Key, fn: Callable, *args, **statics):
        """``fn(*args, **statics)``: by the prepared program once it is ready (waiting for one
        being compiled), else by the jit (which compiles on the spot the first time)."""
        with self._lock:
            thread = self.pending.get(key)
        if thread is not None:
            thread.join()
        compiled = self.ready.get(key)
        if compiled is not None:
            return compiled(*args)
        return fn(*args, **statics)

    def wait(self) -> None:
        """Join every compilation still running (before the process moves on)."""
        for thread in list(self.pending.values()):
            thread.join()


def direct(key: Key, fn: Callable, *args, **statics):
    """``Programs``' call without programs prepared: the jit itself."""
    del key
    return fn(*args, **statics)
