"""GPU time by kernel from a profiler trace (``jax.profiler.trace(..., create_perfetto_trace=True)``)."""

from __future__ import annotations

import collections
import gzip
import json
import tempfile
from collections.abc import Callable
from pathlib import Path


def kernel_summary(trace_dir: Path, calls: int, top: int = 30) -> dict:
    """Device time per kernel name in the newest perfetto trace under ``trace_dir``, per traced
    call (``calls`` of them): total busy ms per call and the ``top`` kernels by time, each with
    its launches per call. Only device streams count (processes named ``/device:...``); on a
    CPU backend, where no such process exists, the host's XLA threads are summed instead."""
    traces = sorted(Path(trace_dir).rglob("perfetto_trace.json.gz"), key=lambda p: p.stat().st_mtime)
    if not traces:
        return {"error": f"no perfetto_trace.json.gz under {trace_dir}"}
    with gzip.open(traces[-1]) as f:
        events = json.load(f)["traceEvents"]
    names = {e["pid"]: e["args"]["name"] for e in events if e.get("ph") == "M" and e.get("name") == "process_name"}
    device = {pid for pid, name in names.items() if name.startswith("/device:")}
    keep = device or {pid for pid, name in names.items() if name.startswith("/host:")}
    total, count, details = collections.Counter(), collections.Counter(), {}
    for e in events:
        if e.get("ph") == "X" and e.get("pid") in keep and "dur" in e:
            total[e["name"]] += e["dur"]
            count[e["name"]] += 1
            details.setdefault(e["name"], _launch_details(e.get("args") or {}))
    busy_us = sum(total.values())
    return {"source": "device streams" if device else "host threads (no device process)",
            "busy_ms_per_call": round(busy_us / 1e3 / calls, 3),
            "kernels": [{"name": name[:120], "ms_per_call": round(us / 1e3 / calls, 3),
                         "share": round(us / max(busy_us, 1), 4), "launches_per_call": round(count[name] / calls, 2),
                         **({"launch": details[name]} if details.get(name) else {})}
                        for name, us in total.most_common(top)]}


def _launch_details(args: dict) -> str:
    """What the GPU tracer recorded about a kernel's launch (registers a thread, shared memory,
    grid, block, occupancy), as one short string ('' where it recorded none: a CPU)."""
    keys = ("kernel_details", "theoretical_occupancy_pct")
    return "; ".join(f"{k}={str(args[k])[:200]}" for k in keys if k in args)


def traced(work: Callable[[], None], repeats: int, trace_dir: Path | None = None, top: int = 30,
           calls_per_work: int = 1) -> dict:
    """``kernel_summary`` per call of ``work()`` run ``repeats`` times under the profiler (each run
    blocks until its device work is done; one run makes ``calls_per_work`` calls); the trace is
    kept in ``trace_dir``, else in a folder removed after."""
    import jax

    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(trace_dir) if trace_dir is not None else Path(scratch)
        folder.mkdir(parents=True, exist_ok=True)
        with jax.profiler.trace(str(folder), create_perfetto_trace=True):
            for _ in range(repeats):
                work()
        return kernel_summary(folder, calls=repeats * calls_per_work, top=top)
