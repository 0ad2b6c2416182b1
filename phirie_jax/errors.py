"""Errors meant for people: each names the file, the field and what was expected."""

from __future__ import annotations

from pathlib import Path


class SceneInputError(ValueError):
    """Bad input data. The message is one line: ``FILE: FIELD: what was wrong (expected ...)``.

    The CLI prints it as that one line (no traceback) and exits non-zero.
    """

    def __init__(self, path: str | Path | None, field: str | None, problem: str):
        self.path = None if path is None else Path(path)
        self.field = field
        self.problem = problem
        parts = [str(p) for p in (self.path, field) if p is not None]
        parts.append(problem)
        super().__init__(": ".join(parts))
