"""The collision workers never outlive the run: a ``kill -9`` of the process that started them
takes them along (``native.die_with_parent``), and Ctrl-C terminates them instead of waiting
for the meshes they are decomposing.

Each test starts a parent process whose one object's "build" records its process id and sleeps
far longer than the test, then ends the parent and watches the worker.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.processes import kill_quietly, running, wait_for

ROOT = Path(__file__).resolve().parents[3]
GONE_WITHIN_S = 30.0    # a dead parent's worker is gone this soon (a waiting parent: SLEEP_S; slack for a loaded CPU)
START_WITHIN_S = 60.0   # the parent imports the physics stage and spawns a worker (slow on a loaded CPU)
SLEEP_S = 120.0         # the build's sleep: a worker still there after GONE_WITHIN_S was orphaned

PARENT = """
import signal
import sys
signal.signal(signal.SIGINT, signal.default_int_handler)  # as from a terminal (a test runner's worker may ignore it)
from pathlib import Path
from phirie_jax.construct.physics.config import PhysicsConfig
from phirie_jax.construct.physics.stage import build_objects
from phirie_jax.records import ObjectRecord
from tests.construct.physics.test_workers import sleeping_build
build_objects([ObjectRecord(id=1)], {}, Path(sys.argv[1]), PhysicsConfig(workers=0), build=sleeping_build)
"""


def sleeping_build(entry, category, out_dir, config):
    """(In a worker.) Record this process's id, then sleep as a long CoACD run would."""
    (Path(out_dir) / "worker.pid").write_text(str(os.getpid()))
    time.sleep(SLEEP_S)
    return {"update": {}}


def started_worker(tmp_path: Path) -> tuple[subprocess.Popen, int]:
    """A parent process building one object, and its worker's process id once it is at work."""
    parent = subprocess.Popen([sys.executable, "-c", PARENT, str(tmp_path)], cwd=ROOT)
    pid_file = tmp_path / "worker.pid"
    if not wait_for(lambda: pid_file.is_file() and pid_file.read_text(), START_WITHIN_S):
        parent.kill()
        pytest.fail("the worker did not start")
    return parent, int(pid_file.read_text())


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl(PR_SET_PDEATHSIG) is Linux's")
def test_a_killed_parent_takes_its_workers_along(tmp_path):
    parent, worker = started_worker(tmp_path)
    try:
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
        assert wait_for(lambda: not running(worker), GONE_WITHIN_S), "the worker outlived its killed parent"
    finally:
        kill_quietly(worker)


def test_an_interrupted_parent_terminates_its_workers_at_once(tmp_path):
    parent, worker = started_worker(tmp_path)
    try:
        os.kill(parent.pid, signal.SIGINT)
        try:
            parent.wait(timeout=GONE_WITHIN_S)
        except subprocess.TimeoutExpired:
            parent.kill()
            pytest.fail("the interrupted parent waited for its worker's build")
        assert parent.returncode != 0
        assert wait_for(lambda: not running(worker), GONE_WITHIN_S), "the worker outlived the interrupted run"
    finally:
        kill_quietly(worker)


def environment_build(entry, category, out_dir, config):
    """(In a worker.) The OpenMP settings this worker's native libraries will read, and its niceness."""
    return {"update": {"omp": os.environ.get("OMP_NUM_THREADS"), "wait": os.environ.get("OMP_WAIT_POLICY"),
                       "nice": os.nice(0)}}


def test_each_worker_gets_twice_its_share_of_the_cores_at_a_lower_priority(tmp_path, monkeypatch):
    from phirie_jax.construct.physics.config import CoacdConfig, PhysicsConfig
    from phirie_jax.construct.physics.stage import OPENMP_OVERSUBSCRIPTION, build_objects, worker_threads
    from phirie_jax.records import ObjectRecord

    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    entries = [ObjectRecord(id=1), ObjectRecord(id=2)]
    ours = os.nice(0)
    shared = build_objects(entries, {}, tmp_path, PhysicsConfig(workers=2), build=environment_build)
    cores = os.cpu_count() or 1
    threads = str(max(1, min(cores, OPENMP_OVERSUBSCRIPTION * cores // 2)))
    assert worker_threads(1, PhysicsConfig()) == cores   # a lone worker: at most the cores
    lowered = min(19, ours + CoacdConfig().niceness)
    assert [o["update"] for o in shared] == [{"omp": threads, "wait": "PASSIVE", "nice": lowered}] * 2
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")   # the user's own setting stays
    told = build_objects(entries[:1], {}, tmp_path, PhysicsConfig(workers=4, coacd=CoacdConfig(threads=3, niceness=0)),
                         build=environment_build)
    assert told[0]["update"] == {"omp": "3", "wait": "ACTIVE", "nice": ours}


def identity_build(entry, category, out_dir, config):
    """(In a worker.) The entry's id."""
    return {"update": {"built": entry.id}}


def test_the_largest_meshes_start_first_and_the_outcomes_keep_their_order(tmp_path):
    from phirie_jax.construct.physics.config import PhysicsConfig
    from phirie_jax.construct.physics.stage import build_objects, longest_first
    from phirie_jax.records import ObjectRecord

    for ident, size in ((1, 10), (2, 3000), (5, 200)):
        (tmp_path / f"{ident}.obj").write_text("v 0 0 0\n" * size)
    entries = [ObjectRecord(id=1, mesh="1.obj"), ObjectRecord(id=2, mesh="2.obj"), ObjectRecord(id=3),
               ObjectRecord(id=4, mesh="missing.obj"), ObjectRecord(id=5, mesh=str(tmp_path / "5.obj"))]
    assert longest_first(entries, tmp_path) == [1, 4, 0, 2, 3]             # no mesh or no file: last, in order
    outcomes = build_objects(entries, {}, tmp_path, PhysicsConfig(workers=2), build=identity_build)
    assert [o["update"]["built"] for o in outcomes] == [1, 2, 3, 4, 5]
