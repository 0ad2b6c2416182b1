"""Timing shared by the benchmarks: the first call (compilation included) apart from the
median of the calls after it."""

from __future__ import annotations

import statistics
import time

import jax


def timed(fn, repeats: int) -> tuple[float, float]:
    """(first call s, median of ``repeats`` later calls s; the first call's time when ``repeats``
    is 0); results are blocked on."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return first, statistics.median(times) if times else first


def timed_steps(batch, steps: int, repeats: int) -> tuple[float, float]:
    """``timed`` for ``batch.step(steps)`` of batched worlds, waiting on their state."""
    return timed(lambda: (batch.step(steps), batch.data.qpos)[1], repeats)
