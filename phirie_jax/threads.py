"""Independent pieces of host work on every core, their results in order.

For loops whose bodies spend their time in code that lets go of the interpreter (NumPy's
sorts and arithmetic, OpenCV, SciPy): one view, one photo at a time. The results are those of
the plain loop, in the same order; an exception in a piece is raised as the loop would raise it.
SciPy's own split of a nearest-neighbour query over the cores is chosen by ``query_workers``.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")

# points: a nearest-neighbour query of fewer runs on one thread. A few thousand points take
# milliseconds, and split over cores that other processes keep busy (the CoACD workers beside the
# background stage) they took 1.7x longer than on one thread (docs/performance.md, the removal's
# queries on crowded; measured on 2 cores, not on the 16-core GPU host).
SMALL_QUERY = 50_000


def query_workers(count: int) -> int:
    """SciPy's ``workers`` for a query of ``count`` points: every core (-1), or one thread for a
    query below ``SMALL_QUERY``."""
    return -1 if count >= SMALL_QUERY else 1


def map_on_cores(fn: Callable[[T], R], items: Iterable[T], name: str = "host work", workers: int = 0) -> list[R]:
    """``[fn(item) for item in items]``, up to ``workers`` threads at once (0: one per core)."""
    items = list(items)
    workers = min(len(items), workers or os.cpu_count() or 1)
    if workers <= 1:
        return [fn(item) for item in items]
    with ThreadPoolExecutor(workers, thread_name_prefix=name) as pool:
        return list(pool.map(fn, items))
