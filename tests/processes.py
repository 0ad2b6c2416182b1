"""Watching child processes in tests: is one still running, wait for a condition, end one."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path


def running(pid: int) -> bool:
    """The process exists and is not a zombie (a killed orphan waits for PID 1 to reap it)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state != "Z"


def wait_for(predicate, seconds: float) -> bool:
    """Poll ``predicate`` until it holds or ``seconds`` pass; whether it held."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return bool(predicate())


def kill_quietly(pid: int) -> None:
    """SIGKILL ``pid`` if it is still there (a test's cleanup after a failed assertion)."""
    try:
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
