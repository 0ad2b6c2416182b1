"""Valid ranges of numeric settings, checked where each config is made.

A stage config's ``__post_init__`` calls ``check_ranges(self, {"voxel": POSITIVE, ...})``: a value
outside its range raises ``ConfigValueError`` naming the config, the field, the value and the
range, so a bad number fails where it is set rather than as a division by zero minutes later.

The command line builds its configs from the options with these checks deferred
(``deferred_checks``), then checks the whole tree again (``check_options``) where it knows each
field's option, and reports one line such as ``--config.observe.voxel -1: expected > 0`` before
any work starts. Deferring is needed because tyro turns a ``ValueError`` raised while it builds a
config into a boxed message that names the config rather than the option.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import numbers
import typing
from collections.abc import Iterator
from contextvars import ContextVar

import numpy as np

from phirie_jax.errors import ConfigValueError, OptionError

_deferred: ContextVar[bool] = ContextVar("phirie_range_checks_deferred", default=False)


@dataclasses.dataclass(frozen=True)
class Range:
    """Finite numbers between ``low`` and ``high`` (None: unbounded on that side), each end
    included unless marked open. ``bound`` says, in the message, where a bound comes from
    (another field: ``truncation`` ≥ ``voxel``) or what it means ("0 = the photos' size")."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    bound: str | None = None

    def __contains__(self, value) -> bool:
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
            return False
        if self.low is not None and (value <= self.low if self.low_open else value < self.low):
            return False
        return self.high is None or (value < self.high if self.high_open else value <= self.high)

    def __str__(self) -> str:
        low, high = shown(self.low), shown(self.high)
        if self.low is not None and self.high is not None:
            text = f"in {'(' if self.low_open else '['}{low}, {high}{')' if self.high_open else ']'}"
        elif self.low is not None:
            text = f"{'>' if self.low_open else '≥'} {low}"
        elif self.high is not None:
            text = f"{'<' if self.high_open else '≤'} {high}"
        else:
            text = "a finite number"
        return text if self.bound is None else f"{text} ({self.bound})"


@dataclasses.dataclass(frozen=True)
class Each:
    """A tuple of at least ``count`` values, each in ``range`` (and increasing when asked)."""

    range: Range
    count: int = 1
    increasing: bool = False

    def __contains__(self, values) -> bool:
        values = tuple(values)
        ordered = not self.increasing or all(a < b for a, b in zip(values, values[1:]))
        return len(values) >= self.count and ordered and all(v in self.range for v in values)

    def __str__(self) -> str:
        values = "increasing values" if self.increasing else "values"
        many = "one or more" if self.count == 1 else f"at least {self.count}"
        return f"{many} {values}, each {self.range}"


@dataclasses.dataclass(frozen=True)
class Positions:
    """A tuple whose k-th value is in ``ranges[k]``."""

    ranges: tuple[Range, ...]

    def __contains__(self, values) -> bool:
        values = tuple(values)
        return len(values) == len(self.ranges) and all(v in r for v, r in zip(values, self.ranges))

    def __str__(self) -> str:
        return "values " + ", ".join(str(r) for r in self.ranges)


@dataclasses.dataclass(frozen=True)
class Choice:
    """One of a field's named options: the values of its ``Literal`` type (``Choice.of(Backend)``)."""

    options: tuple[str, ...]

    @classmethod
    def of(cls, literal) -> Choice:
        """The options of a ``Literal[...]`` of strings (a field typed ``Alias | None``: None is unset
        and passes, as for every spec)."""
        options = typing.get_args(literal)
        if typing.get_origin(literal) is not typing.Literal or not all(isinstance(o, str) for o in options):
            raise TypeError(f"Choice.of: {literal!r} is not a Literal of strings")
        return cls(options)

    def __contains__(self, value) -> bool:
        return isinstance(value, str) and value in self.options

    def __str__(self) -> str:
        return "one of " + ", ".join(self.options)


Spec = Range | Each | Positions | Choice

POSITIVE = Range(0, low_open=True)
NON_NEGATIVE = Range(0)
AT_LEAST_ONE = Range(1)
FRACTION = Range(0, 1)                      # [0, 1]
OPEN_FRACTION = Range(0, 1, True, True)     # (0, 1)
POSITIVE_FRACTION = Range(0, 1, low_open=True)  # (0, 1]
ANGLE_DEG = Range(0, 90)                    # a tilt from up, degrees


def at_least(value: float, bound: str) -> Range:
    """≥ another field's ``value`` (``bound`` names that field)."""
    return Range(value, bound=bound)


def at_most(value: float, bound: str, low: float | None = None) -> Range:
    """≤ another field's ``value`` (and ≥ ``low`` when given)."""
    return Range(low, value, bound=bound)


def shown(value) -> str:
    """A value as it would be typed on a command line: -1 for -1.0, 0.005, 1e-09, ``1 4 16`` for a tuple."""
    if isinstance(value, (tuple, list)):
        return " ".join(shown(v) for v in value) if value else "(none)"
    if isinstance(value, (float, np.floating)):
        return f"{value:g}"
    return str(value)


def _value(config, field: str):
    for part in field.split("."):
        config = getattr(config, part)
    return config


def check_ranges(config, ranges: dict[str, Spec]) -> None:
    """Raise ``ConfigValueError`` for the first field of ``config`` outside its range.

    Keys are field names (dotted for a field of a nested dataclass: ``search.num_yaws``); a field
    whose value is None is unset and passes. Nothing is checked inside ``deferred_checks``.
    """
    if _deferred.get():
        return
    for field, spec in ranges.items():
        value = _value(config, field)
        if value is not None and value not in spec:
            expected = str(spec)
            bounded = isinstance(spec, Range) and (spec.low is not None or spec.high is not None)
            if bounded and isinstance(value, numbers.Real) and not math.isfinite(value):
                expected = f"a finite number {expected}"
            raise ConfigValueError(type(config).__name__, field, shown(value), expected)


def check_option(option: str, value, spec: Spec) -> None:
    """A plain command-line option (not a config field) in its range, else ``OptionError``
    (``--width 0: expected > 0``). None (not given) passes."""
    if value is not None and value not in spec:
        raise OptionError(option, f"expected {spec}", shown(value))


@contextlib.contextmanager
def deferred_checks() -> Iterator[None]:
    """Inside, ``check_ranges`` checks nothing, until ``resume_checks`` (or ``check_options``)
    ends the deferral early; the checks are back on after the block in any case."""
    token = _deferred.set(True)
    try:
        yield
    finally:
        _deferred.reset(token)


def resume_checks() -> None:
    """End ``deferred_checks`` early: what runs from here on checks its configs again."""
    _deferred.set(False)


def check_options(config, option: str) -> None:
    """Resume the checks and make them again on ``config`` and every config nested in it, the
    innermost first (a bad inner value is the cause of an outer one's failure). A value out of
    range raises ``OptionError`` naming the whole option: ``option`` for ``config`` itself
    ("--config"), then the field path in the command line's spelling (``-`` for ``_``)."""
    resume_checks()
    for path, node in _nested(config, option):
        try:
            node.__post_init__()
        except ConfigValueError as err:
            name = ".".join(part.replace("_", "-") for part in err.field.split("."))
            raise OptionError(f"{path}.{name}", f"expected {err.expected}", err.shown) from None


def _nested(config, path: str) -> Iterator[tuple[str, object]]:
    """(option path, config) of every dataclass instance under ``config`` with a
    ``__post_init__``, children before their parent."""
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            yield from _nested(value, f"{path}.{field.name.replace('_', '-')}")
    if hasattr(config, "__post_init__"):
        yield path, config
