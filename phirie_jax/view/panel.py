"""What the viewer's panel says about each object, as Markdown, from its record (``records.ObjectRecord``)."""

from __future__ import annotations

import math

from phirie_jax.info import STATUS_COLOURS, candidate_name, chosen_scores, drop_verdict, status_words
from phirie_jax.records import ObjectRecord


def _number(value, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "—"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return str(value)
    return f"{value:.{digits}g}"


def object_markdown(entry: ObjectRecord) -> str:
    """The panel of one object: status, candidate and scores, checks, drop test, physics."""
    marker = {"green": "🟢", "yellow": "🟡"}.get(STATUS_COLOURS.get(entry.status, "red"), "🔴")
    lines = [f"{marker} **{status_words(entry)}** · candidate `{candidate_name(entry)}`"]
    if not entry.accepted and entry.reason:
        lines.append(f"reason: {entry.reason}")
    scores = {k: v for k, v in chosen_scores(entry).items() if isinstance(v, (int, float))}
    if scores:
        lines.append("scores: " + ", ".join(f"{k} {_number(v)}" for k, v in scores.items()))
    if entry.checks:
        lines += ["", "| check | value | threshold | |", "|---|---|---|---|"]
        for check in entry.checks:
            mark = "✔" if check.passed else "✘" if check.passed is False else "·"
            lines.append(f"| {check.name} | {_number(check.value)} | {_number(check.threshold)} | {mark} |")
        lines.append("")
    lines.append(f"drop test: {drop_verdict(entry)}")
    physics = entry.physics or {}
    mass = physics.get("mass_properties") or {}
    if entry.mass is not None:
        lines.append(f"mass {_number(entry.mass)} kg · friction {_number(entry.friction)}"
                     + (f" · {len(entry.collision)} convex parts" if entry.collision else ""))
    source = (physics.get("priors") or {}).get("mass_source")
    if source:
        lines.append(f"mass from: {source}")
    if mass.get("com") is not None:
        lines.append("centre of mass (body frame, m): " + ", ".join(_number(v) for v in mass["com"]))
    return "\n".join(lines)
