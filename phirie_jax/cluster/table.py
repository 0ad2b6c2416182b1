"""The terminal's view of ``phirie convert-many``: a line as each scene ends, a table at the end."""

from __future__ import annotations

from rich.console import Console
from rich.markup import escape
from rich.table import Table

STATUS_COLOURS = {"converted": "green", "skipped": "cyan", "failed": "red", "pending": "default"}


def _objects(record: dict) -> str:
    o = record.get("objects")
    return "—" if o is None else f"{o['accepted']}/{o['unverified']}/{o['rejected']}"


def _drops(record: dict) -> str:
    drops = record.get("drop_tests")
    return "—" if not drops or not drops.get("tested") else f"{drops['stable']}/{drops['tested']}"


def _background(record: dict) -> str:
    b = record.get("background")
    return "—" if not b else f"{b.get('removed')}/{b.get('filled')}"


def _frame(record: dict) -> str:
    frame = record.get("frame")
    return "—" if not frame else str(frame.get("scale_source"))


def _number(value, digits: int = 0) -> str:
    return "—" if value is None else f"{value:.{digits}f}"


def ended_line(record: dict) -> str:
    """``phirie: fox: converted in 184 s (1 accepted, 0 unverified, 0 rejected)`` or its reason."""
    text = f"phirie: {record['name']}: {record['status']}"
    if record.get("seconds") is not None:
        text += f" in {record['seconds']:.0f} s"
    objects = record.get("objects")
    if objects and record["status"] != "failed":
        text += (f" ({objects['accepted']} accepted, {objects['unverified']} unverified, "
                 f"{objects['rejected']} rejected)")
    if record.get("took_over") is not None:
        text += f" after taking over from killed process {record['took_over']}"
    if record.get("reason"):
        text += f": {record['reason']}"
    return text


def print_summary(summary: dict, console: Console | None = None) -> None:
    """One row per scene: status, objects by status, drop tests, background (Gaussians removed and
    filled), the frame's scale source, time, peak memory; then the reason of each scene that failed."""
    console = console or Console()
    counts = ", ".join(f"{n} {s}" for s, n in summary["counts"].items())
    table = Table(title=f"phirie convert-many: {summary['root']} ({summary['seconds']:.0f} s, {counts})",
                  caption="objects: accepted/unverified/rejected; drops: stable/tested drop tests; background: "
                          "Gaussians removed/filled; frame: where the scale came from; MiB: peak memory of the "
                          "task's process or its largest child")
    for column in ("scene", "status", "objects", "drops", "background", "frame", "s", "MiB"):
        table.add_column(column, justify="right" if column in ("s", "MiB") else "left",
                         no_wrap=column != "frame", min_width=8 if column == "frame" else None)
    for r in summary["scenes"]:
        colour = STATUS_COLOURS.get(r["status"], "default")
        peak = max((v for v in (r.get("peak_memory_mb"), r.get("peak_memory_children_mb")) if v is not None),
                   default=None)
        table.add_row(escape(r["name"]), f"[{colour}]{r['status']}[/]", _objects(r), _drops(r), _background(r),
                      escape(_frame(r)), _number(r.get("seconds")), _number(peak))
    console.print(table)
    for r in summary["scenes"]:
        if r.get("reason"):
            console.print(f"[red]{escape(r['name'])}[/]: {escape(r['reason'])}", soft_wrap=True)
