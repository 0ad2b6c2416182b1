"""Native code that may crash, run in a child process so a crash becomes a Python error.

Open3D's ``VoxelBlockGrid`` and CoACD are C++ libraries: an overflow or an assertion in them
ends the process with a signal (SIGSEGV, SIGABRT) and no traceback, after minutes of work.
``run_isolated`` runs a picklable top-level function in a fresh interpreter
(``sys.executable``) and returns its result; a child that dies raises
``NativeLibraryError`` naming the library and the signal.

A fresh interpreter rather than ``multiprocessing``: its spawn and forkserver start methods
re-run the caller's main script in the child (a script without an ``if __name__ ==
"__main__"`` guard would render the whole scene again there), and fork copies the parent's
JAX threads. The call, its arguments and the result travel pickled through pipes (NumPy
arrays included); the child's stdout and stderr are the parent's, so the library's own
messages still reach the user. The cost is the interpreter's start and the imports of the
function's module (measured in ``tests/observe/test_native.py``).

A child never outlives its parent: ``die_with_parent`` asks Linux to kill it when the parent
ends, however it ends (``kill -9`` included), so minutes of native work do not go on orphaned.

``IsolatedPool`` runs many such calls, at most ``workers`` at once, each in its own fresh
interpreter (the CoACD decomposition of each object, ``construct.physics.stage``): one
crashing call is that call's ``NativeLibraryError`` and the others go on; ``terminate`` (and
leaving its ``with`` block on an exception: Ctrl-C) kills the running children at once and
drops the queued calls; each child's OpenMP libraries start ``threads`` threads, and its CPU
priority may be lowered (``niceness``) so the parent's own work gets the larger share of the cores.
"""

from __future__ import annotations

import ctypes
import os
import pickle
import signal as signal_mod
import subprocess
import sys
import threading
import traceback
from concurrent.futures import Future, ThreadPoolExecutor

from phirie_jax.errors import NativeLibraryError

# The child: the parent's import path first (so the function's module imports as it does
# here), then the call from stdin; the answer goes to the file descriptor in argv[1]; argv[2] is
# the parent's pid (``die_with_parent``), argv[3] the niceness (``yield_cpu``).
_BOOTSTRAP = ("import pickle, sys\n"
              "stream = sys.stdin.buffer\n"
              "sys.path[:0] = pickle.load(stream)\n"
              "from phirie_jax.native import die_with_parent, serve, yield_cpu\n"
              "die_with_parent(int(sys.argv[2]))\n"
              "yield_cpu(int(sys.argv[3]))\n"
              "serve(stream, int(sys.argv[1]))\n")
_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def die_with_parent(parent_pid: int) -> None:
    """(In a child.) Be killed (SIGKILL) when the process ``parent_pid`` that started this one
    ends; exit now if it has already ended. Linux only (``prctl(PR_SET_PDEATHSIG)``); elsewhere
    nothing is done.

    The signal follows the thread that started the child: ``run_isolated`` and the worker pool
    start their children from the thread that waits for them, so it lives as long as they work.
    """
    if not sys.platform.startswith("linux"):
        return
    libc = ctypes.CDLL(None, use_errno=True)  # this process's own symbols: libc's prctl among them
    if libc.prctl(_PR_SET_PDEATHSIG, signal_mod.SIGKILL, 0, 0, 0) != 0:
        return  # refused (a restricted sandbox): the child can then outlive a killed parent
    if os.getppid() != parent_pid:  # the parent died before the request was made
        os._exit(1)


def yield_cpu(niceness: int) -> None:
    """(In a child, before it starts any thread.) Lower this process's CPU priority by
    ``niceness`` (Unix ``nice``, at most to 19; 0: unchanged), so the parent's work gets the larger
    share of busy cores (at nice 10, about nine times a child's). Threads started afterwards (an
    OpenMP team) inherit it. Where the system refuses, the child runs at the parent's priority."""
    if niceness > 0 and hasattr(os, "nice"):
        try:
            os.nice(niceness)
        except OSError:
            pass


def serve(stream, answer_fd: int) -> None:
    """(In the child.) Read (fn, args, kwargs) from ``stream``, write ("ok", result) or
    ("raised", (exception or None, traceback text)) to ``answer_fd``."""
    try:
        fn, args, kwargs = pickle.load(stream)
        message = ("ok", fn(*args, **kwargs))
    except BaseException as err:  # noqa: BLE001 — every failure goes back to the parent
        text = "".join(traceback.format_exception(err))
        try:
            pickle.loads(pickle.dumps(err))  # some exceptions pickle but do not unpickle
            message = ("raised", (err, text))
        except Exception:  # noqa: BLE001 — such an exception travels as text
            message = ("raised", (None, text))
    with os.fdopen(answer_fd, "wb") as out:
        pickle.dump(message, out, protocol=pickle.HIGHEST_PROTOCOL)


def signal_name(returncode: int) -> str | None:
    """'SIGSEGV' for the return code −11 of a process killed by signal 11; None otherwise."""
    if returncode >= 0:
        return None
    try:
        return signal_mod.Signals(-returncode).name
    except ValueError:
        return None


class _Children:
    """The children an ``IsolatedPool`` has running; once closed, a child that starts is killed."""

    def __init__(self):
        self._lock = threading.Lock()
        self._running: set[subprocess.Popen] = set()
        self.closed = False

    def add(self, child: subprocess.Popen) -> None:
        with self._lock:
            self._running.add(child)
            if self.closed:
                child.kill()

    def discard(self, child: subprocess.Popen) -> None:
        with self._lock:
            self._running.discard(child)

    def pids(self) -> list[int]:
        with self._lock:
            return [child.pid for child in self._running]

    def kill_all(self) -> None:
        with self._lock:
            self.closed = True
            for child in self._running:
                child.kill()


def run_isolated(library: str, fn, *args, description: str | None = None, env: dict[str, str] | None = None,
                 children: _Children | None = None, niceness: int = 0, **kwargs):
    """``fn(*args, **kwargs)`` in a child process; its result, or the exception it raised.

    library: the native library ``fn`` calls (named in the error); description: what was
    being done ("VoxelBlockGrid fusion"), also in the error; env: variables set in the child
    besides this process's; children: where an ``IsolatedPool`` keeps the child while it runs;
    niceness: how much lower the child's CPU priority is than this process's (``yield_cpu``).
    ``fn`` must be a top-level function of an importable module. Raises ``NativeLibraryError``
    when the child dies (a signal, or an exit without an answer), e.g.
    "Open3D VoxelBlockGrid fusion died with signal 11 (SIGSEGV)"; an exception that cannot
    travel back comes as a RuntimeError with the child's traceback.
    """
    what = f"{description} " if description else ""
    payload = pickle.dumps((fn, args, kwargs), protocol=pickle.HIGHEST_PROTOCOL)  # fails here, not in the child
    read_fd, write_fd = os.pipe()
    try:
        child = subprocess.Popen([sys.executable, "-c", _BOOTSTRAP, str(write_fd), str(os.getpid()),
                                  str(int(niceness))],
                                 stdin=subprocess.PIPE, pass_fds=(write_fd,),
                                 env=None if env is None else {**os.environ, **env})
    finally:
        os.close(write_fd)  # the child holds the only writing end: its death reads as EOF here
    if children is None:
        return _answer(child, read_fd, payload, library, what)
    children.add(child)
    try:
        return _answer(child, read_fd, payload, library, what)
    finally:
        children.discard(child)


def _answer(child: subprocess.Popen, read_fd: int, payload: bytes, library: str, what: str):
    """Send the call to ``child``, wait for it, and return its result (``run_isolated``)."""
    chunks: list[bytes] = []
    reader = threading.Thread(target=lambda: chunks.append(_read_all(read_fd)), daemon=True)
    reader.start()  # drain the answer while the call is still being written (both may be large)
    try:
        with child.stdin:
            pickle.dump(list(sys.path), child.stdin)
            child.stdin.write(payload)
    except BrokenPipeError:  # the child died before reading it all; its return code says why
        pass
    returncode = child.wait()
    reader.join()
    answer = chunks[0] if chunks else b""
    if answer:
        status, value = pickle.loads(answer)
        if status == "ok":
            return value
        err, text = value
        if err is not None:
            raise err
        raise RuntimeError(f"{library} {what}failed in its child process:\n{text}")
    name = signal_name(returncode)
    if name is not None:
        raise NativeLibraryError(library, f"{what}died with signal {-returncode} ({name})", name)
    if returncode < 0:
        raise NativeLibraryError(library, f"{what}died with signal {-returncode}", f"signal {-returncode}")
    raise NativeLibraryError(library, f"{what}exited with code {returncode} without a result")


def _read_all(fd: int) -> bytes:
    with os.fdopen(fd, "rb") as f:
        return f.read()


class IsolatedPool:
    """``run_isolated`` calls of one native ``library``, at most ``workers`` at a time, each in a
    fresh interpreter whose OpenMP libraries start ``threads`` threads (0: their own default), at
    a CPU priority ``niceness`` lower than this process's (``yield_cpu``).

    With ``threads`` given, the children's idle OpenMP threads sleep instead of spinning
    (``OMP_WAIT_POLICY=PASSIVE``, unless this process's environment says otherwise): several
    children's teams share the cores.

    ``submit`` returns a ``Future`` of the call's result (or its exception: a crash is a
    ``NativeLibraryError``). Used as a context manager, it waits for the calls on a normal exit
    and ``terminate``s them when the block raises (Ctrl-C's KeyboardInterrupt above all)."""

    def __init__(self, library: str, workers: int, threads: int = 0, niceness: int = 0):
        self.library = library
        self.env = None
        if threads > 0:
            self.env = {"OMP_NUM_THREADS": str(threads),
                        "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE")}
        self.niceness = niceness
        self._children = _Children()
        self._threads = ThreadPoolExecutor(max(1, workers), thread_name_prefix=f"{library} call")

    def submit(self, fn, *args, description: str | None = None) -> Future:
        return self._threads.submit(run_isolated, self.library, fn, *args, description=description,
                                    env=self.env, children=self._children, niceness=self.niceness)

    def running_pids(self) -> list[int]:
        """Process ids of the children running a call now."""
        return self._children.pids()

    def terminate(self) -> None:
        """Kill the running children now and drop the queued calls (their futures are cancelled;
        a running one's raises ``NativeLibraryError`` with SIGKILL)."""
        self._threads.shutdown(wait=False, cancel_futures=True)
        self._children.kill_all()

    def shutdown(self) -> None:
        """Wait for every submitted call, then release the threads."""
        self._threads.shutdown(wait=True)

    def __enter__(self) -> IsolatedPool:
        return self

    def __exit__(self, kind, err, trace) -> None:
        if kind is None:
            self.shutdown()
        else:
            self.terminate()
