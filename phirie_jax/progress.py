"""Progress of the long steps, for people: the steps say what they do, the command says how it shows.

A step wraps its work in ``task(description, total)`` and calls the ``Handle`` it yields after
each unit (an object decomposed, a refinement step, a rendered frame). Nothing is shown unless a
command has installed a display with ``showing``:

* ``TerminalDisplay``: rich progress bars (a spinner and the elapsed time for a task without a
  total), for a terminal;
* ``PlainDisplay``: plain lines, for a log or CI — one when a task starts, one at each quarter of a
  counted task, one when it ends with its elapsed time.

``display_for(console)`` picks by whether the console is a terminal. The installed display is a
context variable: the stages call ``task`` without knowing who, if anyone, is watching.
"""

from __future__ import annotations

import contextlib
import sys
import time
from collections.abc import Callable, Iterator
from contextvars import ContextVar
from typing import TextIO

QUARTERS = (0.25, 0.5, 0.75)


class Handle:
    """What ``task`` yields: call it to advance (``handle(n=1)``); ``update(text)`` says what the
    task is doing now (a terminal shows it; plain lines do not repeat it)."""

    def __init__(self, advance: Callable[[int], None] = lambda n=1: None,
                 describe: Callable[[str], None] = lambda text: None):
        self._advance, self._describe = advance, describe

    def __call__(self, n: int = 1) -> None:
        self._advance(n)

    def update(self, text: str) -> None:
        self._describe(text)


class PlainDisplay:
    """Lines with elapsed times (module docstring), flushed as they are written."""

    def __init__(self, stream: TextIO | None = None, prefix: str = "phirie: "):
        self.stream = stream
        self.prefix = prefix
        self.depth = 0

    def _line(self, text: str, depth: int) -> None:
        print(f"{self.prefix}{'  ' * depth}{text}", file=self.stream or sys.stdout, flush=True)

    @contextlib.contextmanager
    def task(self, description: str, total: int | None) -> Iterator[Handle]:
        start, depth = time.perf_counter(), self.depth
        self._line(f"{description}" + (f" (0/{total})" if total else ""), depth)
        done, marks = 0, list(QUARTERS)

        def advance(n: int = 1) -> None:
            nonlocal done
            done += n
            while total and marks and done < total and done >= marks[0] * total:
                marks.pop(0)
                self._line(f"{description}: {done}/{total} ({time.perf_counter() - start:.0f} s)", depth)

        self.depth += 1
        try:
            yield Handle(advance)
        finally:
            self.depth -= 1
            count = f"{done}/{total}, " if total else ""
            self._line(f"{description}: done ({count}{time.perf_counter() - start:.1f} s)", depth)


class TerminalDisplay:
    """rich progress bars on a terminal (module docstring)."""

    def __init__(self, console=None):
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            SpinnerColumn,
            TextColumn,
            TimeElapsedColumn,
        )

        self.progress = Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(),
                                 MofNCompleteColumn(), TimeElapsedColumn(), console=console, transient=False)
        self.depth = 0

    def __enter__(self) -> "TerminalDisplay":
        self.progress.start()
        return self

    def __exit__(self, *exc) -> None:
        self.progress.stop()

    @contextlib.contextmanager
    def task(self, description: str, total: int | None) -> Iterator[Handle]:
        indent = "  " * self.depth
        ident = self.progress.add_task(indent + description, total=total)
        self.depth += 1
        try:
            yield Handle(lambda n=1: self.progress.advance(ident, n),
                         lambda text: self.progress.update(ident, description=indent + text))
        finally:
            self.depth -= 1
            if total is None:  # a finished task without a count shows a full bar
                self.progress.update(ident, total=1, completed=1)
            self.progress.stop_task(ident)


_display: ContextVar[PlainDisplay | TerminalDisplay | None] = ContextVar("phirie_progress_display", default=None)


@contextlib.contextmanager
def task(description: str, total: int | None = None) -> Iterator[Handle]:
    """Report a step to the installed display (none: nothing shown); yields its ``Handle``."""
    display = _display.get()
    if display is None:
        yield Handle()
        return
    with display.task(description, total) as advance:
        yield advance


@contextlib.contextmanager
def showing(display: PlainDisplay | TerminalDisplay) -> Iterator[None]:
    """Install ``display`` for the block (a terminal display is started and stopped with it)."""
    token = _display.set(display)
    try:
        if isinstance(display, TerminalDisplay):
            with display:
                yield
        else:
            yield
    finally:
        _display.reset(token)


def display_for(console=None) -> PlainDisplay | TerminalDisplay:
    """Bars on a terminal, plain lines elsewhere (``console``: a rich Console; default stdout's)."""
    from rich.console import Console

    console = console or Console()
    return TerminalDisplay(console) if console.is_terminal else PlainDisplay()
