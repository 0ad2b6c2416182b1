"""How ``WarpWorlds`` launches its units of work (steps, ticks) on GPUs, with a stand-in for
``warp`` that records what runs where: every part runs exactly the units asked for, its graph is
captured once and replayed, and several GPUs launch their graphs from a thread each while a
single GPU launches from the calling thread. (What the graphs compute is MuJoCo Warp's; the
Warp worlds' own tests step it on the CPU, and the GPU benchmarks time this path.)"""

from __future__ import annotations

import contextlib
import sys
import threading
import types

import pytest

from phirie_jax.interact.warp_worlds import WarpWorlds, _Part


class _StandInWarp(types.ModuleType):
    """``ScopedDevice``, ``ScopedCapture`` and ``capture_launch``: units run while no capture is
    open, are recorded into the graph while one is, and a launched graph runs its units again."""

    def __init__(self):
        super().__init__("warp")
        self.capturing: list | None = None
        self.launch_threads: list[str] = []
        self._lock = threading.Lock()

    @contextlib.contextmanager
    def ScopedDevice(self, device):  # noqa: N802 (warp's name)
        yield

    @contextlib.contextmanager
    def ScopedCapture(self):  # noqa: N802
        self.capturing = []
        capture = types.SimpleNamespace(graph=None)
        yield capture
        capture.graph, self.capturing = tuple(self.capturing), None

    def capture_launch(self, graph):
        with self._lock:
            self.launch_threads.append(threading.current_thread().name)
        for unit in graph:
            unit()


def _worlds(devices: list[str]) -> tuple[WarpWorlds, list]:
    """WarpWorlds with only its parts (no model), and per part a list counting its units run."""
    worlds = object.__new__(WarpWorlds)
    worlds.parts = [_Part(device=d, rows=slice(0, 1), model=None, data=None) for d in devices]
    return worlds, [[] for _ in devices]


def _units(warp: _StandInWarp, ran: list) -> list:
    """Per part a unit that runs (counted) or, inside a capture, is recorded for its graph."""
    def unit(k: int):
        def run():
            ran[k].append(1)

        def one():
            if warp.capturing is not None:
                warp.capturing.append(run)
            else:
                run()
        return one
    return [unit(k) for k in range(len(ran))]


@pytest.fixture
def warp(monkeypatch):
    stand_in = _StandInWarp()
    monkeypatch.setitem(sys.modules, "warp", stand_in)
    return stand_in


@pytest.mark.parametrize("devices", [["cuda:0"], ["cuda:0", "cuda:1"], ["cpu"]])
@pytest.mark.parametrize("count", [1, 16, 17, 40])
def test_every_part_runs_the_units_asked_for_on_every_call(warp, devices, count):
    """Two calls of ``count`` units of 16-unit graphs: each part runs count units each call
    (the first a plain unit, then its graph, then the rest plainly; later ones replay the graph)."""
    worlds, ran = _worlds(devices)
    units = _units(warp, ran)
    for call in (1, 2):
        worlds._repeat(("step",), count, units, 16)
        assert [len(r) for r in ran] == [count * call] * len(devices)
    captured = [("step",) in p.graphs for p in worlds.parts]
    assert captured == [d.startswith("cuda") and count > 16 for d in devices]


def test_several_gpus_launch_their_graphs_from_a_thread_each(warp):
    """Two GPUs: every graph launch comes from a worker thread; one GPU launches from the caller."""
    for devices, from_workers in ((["cuda:0", "cuda:1"], True), (["cuda:0"], False)):
        warp.launch_threads.clear()
        worlds, ran = _worlds(devices)
        worlds._repeat(("step",), 64, _units(warp, ran), 16)
        assert len(warp.launch_threads) == 3 * len(devices)   # (64 − 1 plain) // 16 graphs each
        caller = threading.current_thread().name
        assert all((name != caller) == from_workers for name in warp.launch_threads)
