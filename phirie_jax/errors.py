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

    def __reduce__(self):  # pickles (e.g. from a child process) with its three arguments
        return type(self), (self.path, self.field, self.problem)


class SurfaceTooLargeError(SceneInputError):
    """The splat-derived surface's TSDF grid would not fit the memory budget.

    Raised before anything is allocated; the message states the bounds of the depth samples,
    the voxel size and the blocks needed against the budget (usually the scene is not in
    metres, or the voxel is too fine for its size).
    """


class NativeLibraryError(RuntimeError):
    """A native library (Open3D, CoACD, ...) killed the process it ran in (a signal such as
    SIGSEGV or SIGABRT, or an exit without a result). ``library`` names it, ``signal`` is the
    signal's name or None."""

    def __init__(self, library: str, problem: str, signal: str | None = None):
        self.library = library
        self.signal = signal
        super().__init__(f"{library} {problem}")


class OptionError(ValueError):
    """An option that cannot be used. The message is one line: ``--OPTION: VALUE (expected ...)``,
    or ``--OPTION VALUE: expected ...`` when ``value`` is given; the CLI prints it without a
    traceback and exits non-zero."""

    def __init__(self, option: str, problem: str, value: str | None = None):
        self.option = option
        self.problem = problem
        self.value = value
        super().__init__(f"{option}: {problem}" if value is None else f"{option} {value}: {problem}")

    def __reduce__(self):
        return type(self), (self.option, self.problem, self.value)


class ConfigValueError(ValueError):
    """A config field outside its valid range: ``ObserveConfig.voxel -1: expected > 0``.

    ``owner`` is the config's class name, ``field`` the field (dotted for a nested one, as in
    ``search.num_yaws``), ``shown`` the value as written on a command line and ``expected`` the
    range; the CLI turns it into an ``OptionError`` naming the whole option.
    """

    def __init__(self, owner: str, field: str, shown: str, expected: str):
        self.owner = owner
        self.field = field
        self.shown = shown
        self.expected = expected
        super().__init__(f"{owner}.{field} {shown}: expected {expected}")

    def __reduce__(self):
        return type(self), (self.owner, self.field, self.shown, self.expected)


class StageError(RuntimeError):
    """A stage of a conversion failed (a native library crashed, a budget was exceeded, a bug).
    The manifest records it under ``failed_stage``; the CLI prints this one line."""

    def __init__(self, stage: str, cause: BaseException):
        self.stage = stage
        self.cause = cause
        super().__init__(f"stage {stage} failed: {type(cause).__name__}: {cause}")
