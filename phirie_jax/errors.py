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


class OptionError(ValueError):
    """An option that cannot be used. The message is one line: ``--OPTION: VALUE (expected ...)``;
    the CLI prints it without a traceback and exits non-zero."""

    def __init__(self, option: str, problem: str):
        self.option = option
        self.problem = problem
        super().__init__(f"{option}: {problem}")


class StageError(RuntimeError):
    """A stage of a conversion failed (a native library crashed, a budget was exceeded, a bug).
    The manifest records it under ``failed_stage``; the CLI prints this one line."""

    def __init__(self, stage: str, cause: BaseException):
        self.stage = stage
        self.cause = cause
        super().__init__(f"stage {stage} failed: {type(cause).__name__}: {cause}")
