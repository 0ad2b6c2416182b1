"""Native code that may crash, run in a child process so a crash becomes a Python error.

Open3D's ``VoxelBlockGrid`` and CoACD are C++ libraries: an overflow or an assertion in them
ends the process with a signal (SIGSEGV, SIGABRT) and no traceback, after minutes of work.
``run_isolated`` runs a picklable top-level function in a child started by the
``forkserver`` context (a clean process forked from a small server, so the parent's JAX
threads are not copied) and returns its result; a child that dies raises
``NativeLibraryError`` naming the library and the signal. Arguments and the result travel
pickled through a pipe (NumPy arrays included), so this suits calls that take seconds and
move at most a few hundred MB.
"""

from __future__ import annotations

import multiprocessing
import pickle
import signal as signal_mod
import traceback

from phirie_jax.errors import NativeLibraryError

START_METHOD = "forkserver"


def _child(conn, fn, args, kwargs) -> None:
    """Runs in the child: send ("ok", result) or ("raised", exception or its text)."""
    try:
        result = fn(*args, **kwargs)
        message = ("ok", result)
    except BaseException as err:  # noqa: BLE001 — every failure goes back to the parent
        text = "".join(traceback.format_exception(err))
        try:
            pickle.loads(pickle.dumps(err))  # some exceptions pickle but do not unpickle
            message = ("raised", (err, text))
        except Exception:  # noqa: BLE001 — an exception that does not pickle travels as text
            message = ("raised", (None, text))
    try:
        conn.send(message)
    finally:
        conn.close()


def signal_name(exitcode: int) -> str | None:
    """'SIGSEGV' for the exit code −11 of a process killed by signal 11; None otherwise."""
    if exitcode >= 0:
        return None
    try:
        return signal_mod.Signals(-exitcode).name
    except ValueError:
        return f"signal {-exitcode}"


def run_isolated(library: str, fn, *args, description: str | None = None, **kwargs):
    """``fn(*args, **kwargs)`` in a child process; its result, or the exception it raised.

    library: the native library ``fn`` calls (named in the error); description: what was
    being done ("VoxelBlockGrid fusion"), also in the error. ``fn`` must be a top-level
    function of an importable module. Raises ``NativeLibraryError`` when the child dies
    (signal or exit) without sending a result, e.g.
    "Open3D VoxelBlockGrid fusion died with signal 11 (SIGSEGV)".
    """
    what = f"{description} " if description else ""
    ctx = multiprocessing.get_context(START_METHOD)
    receive, send = ctx.Pipe(duplex=False)
    process = ctx.Process(target=_child, args=(send, fn, args, kwargs), daemon=True)
    process.start()
    send.close()  # the child holds the only sending end: a dead child reads as EOF here
    try:
        status, payload = receive.recv()  # before join: a large result must drain the pipe
    except EOFError:
        status, payload = None, None
    finally:
        receive.close()
        process.join()
    if status == "ok":
        return payload
    if status == "raised":
        err, text = payload
        if err is not None:
            raise err
        raise RuntimeError(f"{library} {what}failed in its child process:\n{text}")
    code = process.exitcode
    name = signal_name(code)
    if name is not None:
        number = -code
        label = name if name.startswith("signal") else f"signal {number} ({name})"
        raise NativeLibraryError(library, f"{what}died with {label}", name)
    raise NativeLibraryError(library, f"{what}exited with code {code} without a result")
