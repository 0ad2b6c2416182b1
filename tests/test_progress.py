"""Progress of long steps: nothing without a display; plain lines (start, quarters, end with elapsed
time, nested steps indented) off a terminal; rich bars on one."""

from __future__ import annotations

import io

from rich.console import Console

from phirie_jax.progress import PlainDisplay, TerminalDisplay, display_for, showing, task


def test_without_a_display_a_task_shows_nothing(capsys):
    with task("quiet", 3) as advance:
        advance()
        advance.update("still quiet")
    assert capsys.readouterr().out == ""


def test_plain_lines_start_quarters_and_end_with_the_elapsed_time():
    stream = io.StringIO()
    with showing(PlainDisplay(stream)):
        with task("stage"):
            with task("step", 8) as advance:
                for _ in range(8):
                    advance()
                    advance.update("not repeated in plain lines")
    lines = stream.getvalue().splitlines()
    assert lines[0] == "phirie: stage"
    assert lines[1] == "phirie:   step (0/8)"
    assert [line.split(" (")[0] for line in lines[2:5]] == ["phirie:   step: 2/8", "phirie:   step: 4/8",
                                                          "phirie:   step: 6/8"]
    assert lines[5].startswith("phirie:   step: done (8/8, ") and lines[5].endswith(" s)")
    assert lines[6].startswith("phirie: stage: done (") and len(lines) == 7
    assert not any("not repeated" in line for line in lines)


def test_terminal_bars_count_and_finish():
    console = Console(file=io.StringIO(), force_terminal=True, width=100)
    display = display_for(console)
    assert isinstance(display, TerminalDisplay)
    with showing(display):
        with task("stage"):
            with task("frames", 5) as advance:
                for _ in range(5):
                    advance()
    tasks = display.progress.tasks
    assert [t.description.strip() for t in tasks] == ["stage", "frames"]
    assert all(t.finished for t in tasks) and tasks[1].completed == 5
    assert isinstance(display_for(Console(file=io.StringIO(), force_terminal=False)), PlainDisplay)
