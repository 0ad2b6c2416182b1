"""The typed records the stages hand each other, and their one serialized form.

Each stage takes records and returns records, as MJX threads ``Data`` through ``forward()``
(``d = smooth.kinematics(m, d)``): the frame stage returns a ``FrameRecord``; observation the
``InstanceRecord`` of every instance; object construction an ``ObjectRecord`` per instance;
physics the objects again (collision, priors, drop test) and a ``PhysicsRecord``; the background a
``BackgroundRecord``. ``manifest.json`` (``phirie_jax.manifest``) is their serialized form: each
record is written with ``to_json`` and read with ``from_json``, nowhere else.

A record types the fields other tools rely on (docs/architecture.md "Contracts") and keeps every
other field of its section as written, in ``extra`` (the stage's detail: scores, timings, reports),
so a manifest read and written again is the same JSON. Records are frozen: a stage that changes
one returns a new one (``dataclasses.replace``, or ``with_fields`` for a field of either kind).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from enum import StrEnum
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from phirie_jax.errors import SceneInputError


class ObjectStatus(StrEnum):
    """An object's status (``objects[].status``; a ``str``, written to JSON as its value)."""

    ACCEPTED = "accepted"       # every check passed
    UNVERIFIED = "unverified"   # kept although a check failed (the reason names the checks)
    REJECTED = "rejected"       # not kept (the reason says why)
    FAILED = "failed"           # its stage failed for it (recorded)


KEPT = (ObjectStatus.ACCEPTED, ObjectStatus.UNVERIFIED)   # objects that are bodies of the scene


def plain(value: Any) -> Any:
    """NumPy scalars/arrays, tuples and paths → JSON values; non-finite floats → None."""
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, np.generic):
        return plain(value.item())
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _matrix(value) -> np.ndarray:
    return np.asarray(value, np.float64)


# field metadata: how the JSON value (not None) becomes the field's value
_MATRIX = {"decode": _matrix}
_TUPLE = {"decode": tuple}


class _Record:
    """JSON ↔ record for the dataclasses below: each field but ``extra`` is the JSON key of its
    name; ``extra`` keeps the other keys in their order."""

    SECTION: ClassVar[str] = ""
    REQUIRED: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def from_json(cls, data: Any, where: str | Path | None = None):
        """The record of a JSON object; ``SceneInputError`` naming ``where`` (the file) and the
        field when it is not one or lacks a required field."""
        if not isinstance(data, Mapping):
            raise SceneInputError(where, cls.SECTION, f"expected an object, got {type(data).__name__}")
        names = {f.name: f for f in dataclasses.fields(cls) if f.name != "extra"}
        for key in cls.REQUIRED:
            if data.get(key) is None:
                raise SceneInputError(where, f"{cls.SECTION}.{key}", "missing (expected a value)")
        known = {}
        for key, f in names.items():
            if key in data:
                value, decode = data[key], f.metadata.get("decode")
                try:
                    known[key] = decode(value) if decode is not None and value is not None else value
                except (TypeError, ValueError, AttributeError) as err:
                    raise SceneInputError(where, f"{cls.SECTION}.{key}", f"{value!r} is not readable ({err})") from None
        return cls(**known, extra={k: v for k, v in data.items() if k not in names})

    def to_json(self) -> dict:
        """The record as JSON values: its fields in order, then ``extra``."""
        out = {f.name: plain(_encoded(f, getattr(self, f.name))) for f in dataclasses.fields(self) if f.name != "extra"}
        out.update(plain(self.extra))
        return out

    def with_fields(self, **values):
        """A copy with ``values`` set: record fields replaced, other keys set in ``extra``."""
        names = {f.name for f in dataclasses.fields(self)} - {"extra"}
        extra = {**self.extra, **{k: v for k, v in values.items() if k not in names}}
        return dataclasses.replace(self, **{k: v for k, v in values.items() if k in names}, extra=extra)


def _encoded(f: dataclasses.Field, value: Any) -> Any:
    """A field's value as JSON values go (its ``encode``, when it has one)."""
    encode = f.metadata.get("encode")
    return encode(value) if encode is not None and value is not None else value


# --- checks -----------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Check:
    """One row of a check table (``checks``: {name: {value, threshold, passed, ...}}).

    ``passed`` is None while the check has not run; ``details`` holds the row's other fields as
    written (``method``, ``status``, ``reason``, the drop test's ``backend`` ...)."""

    name: str
    value: float | None
    threshold: float | None
    passed: bool | None
    details: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    @classmethod
    def from_json(cls, name: str, row: Mapping) -> Check:
        return cls(name, row.get("value"), row.get("threshold"), row.get("passed"),
                   {k: v for k, v in row.items() if k not in ("value", "threshold", "passed")})

    def to_json(self) -> dict:
        return {"value": self.value, "threshold": self.threshold, "passed": self.passed, **self.details}


def checks_from_json(table: Mapping) -> tuple[Check, ...]:
    return tuple(Check.from_json(str(name), row) for name, row in table.items())


def checks_json(checks: tuple[Check, ...]) -> dict:
    return {c.name: c.to_json() for c in checks}


_CHECKS = {"decode": checks_from_json, "encode": checks_json}


# --- the five records --------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class FrameRecord(_Record):
    """The scene frame (``frame``): the Sim(3) from the capture into the metric, +z-up world
    frame every output is written in, and where up and the scale came from."""

    SECTION: ClassVar[str] = "frame"

    capture_to_world: np.ndarray | None = dataclasses.field(default=None, metadata=_MATRIX)   # (4, 4) Sim(3)
    up: np.ndarray | None = dataclasses.field(default=None, metadata=_MATRIX)  # (3,) the world's up (+z)
    capture_up: np.ndarray | None = dataclasses.field(default=None, metadata=_MATRIX)  # (3,) up in capture coordinates
    scale: float | None = None                                     # metres per capture unit
    up_source: str | None = None
    scale_source: str | None = None
    scale_uncertainty: float | None = None
    scale_is_prior: bool | None = None
    support: dict | None = None                                    # the support plane found (world)
    warnings: tuple[str, ...] = dataclasses.field(default=(), metadata=_TUPLE)
    evidence: dict = dataclasses.field(default_factory=dict)
    extra: dict = dataclasses.field(default_factory=dict)

    def up_vector(self) -> np.ndarray:
        """(3,) up (+z when not recorded)."""
        return np.asarray(self.up if self.up is not None else (0.0, 0.0, 1.0), np.float64)


@dataclasses.dataclass(frozen=True, eq=False)
class InstanceRecord(_Record):
    """One observed instance (``instances[]``): its observed points Q_i are in ``points``
    (``observe/instance_<id>.npz``, relative to the output folder)."""

    SECTION: ClassVar[str] = "instances"
    REQUIRED: ClassVar[tuple[str, ...]] = ("id",)

    id: int = 0
    category: str | None = None
    views: tuple[int, ...] = dataclasses.field(default=(), metadata=_TUPLE)
    view_names: tuple[str, ...] | None = dataclasses.field(default=None, metadata=_TUPLE)
    num_points: int | None = None
    bounds: np.ndarray | None = dataclasses.field(default=None, metadata=_MATRIX)  # (2, 3) min, max corner
    source: str | None = None
    points: str | None = None
    confidence: float | None = None
    support: dict | None = None                                    # ``observe.support.Support.as_record``
    extra: dict = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True, eq=False)
class ObjectRecord(_Record):
    """One object (``objects[]``; its id is its instance's). ``pose``: (4, 4) Sim(3), canonical
    mesh → scene, scale included; ``collision``: convex part paths in the canonical frame of
    ``mesh``. ``extra`` holds the stages' detail (``support``, ``unresolved_checks``,
    ``physics``, ``visual_info``, ``time_s`` ...)."""

    SECTION: ClassVar[str] = "objects"
    REQUIRED: ClassVar[tuple[str, ...]] = ("id",)

    id: int = 0
    status: ObjectStatus = dataclasses.field(default=ObjectStatus.FAILED, metadata={"decode": ObjectStatus})
    reason: str | None = None
    candidate: str | None = None
    pose: np.ndarray | None = dataclasses.field(default=None, metadata=_MATRIX)
    mesh: str | None = None
    visual: str | None = None
    collision: tuple[str, ...] = dataclasses.field(default=(), metadata=_TUPLE)
    mass: float | None = None
    friction: float | None = None
    checks: tuple[Check, ...] = dataclasses.field(default=(), metadata=_CHECKS)
    # every candidate tried, with its scores, checks and pose (the object stage's own records)
    candidates: tuple[dict, ...] = dataclasses.field(default=(), metadata=_TUPLE)
    drop_test: dict | None = None
    extra: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "status", ObjectStatus(self.status))   # a word that is no status fails here

    @property
    def kept(self) -> bool:
        """A body of the scene (accepted or unverified)."""
        return self.status in KEPT

    @property
    def accepted(self) -> bool:
        return self.status == ObjectStatus.ACCEPTED

    def check(self, name: str) -> Check | None:
        return next((c for c in self.checks if c.name == name), None)

    @property
    def failed_checks(self) -> list[str]:
        """The names of the checks that ran and failed."""
        return [c.name for c in self.checks if c.passed is False]

    @property
    def unresolved_checks(self) -> list[str] | None:
        """The failed checks the object was kept with (None when the object stage recorded none)."""
        return self.extra.get("unresolved_checks")

    @property
    def physics(self) -> dict | None:
        """The physics stage's record of the body (``body``, ``urdf``, ``priors``, ``mass_properties``...)."""
        return self.extra.get("physics")

    @property
    def mounted(self) -> bool:
        """Welded to the wall behind it where it is placed (the object stage's ``mount`` record)."""
        return bool(self.extra.get("mount"))

    @property
    def support_height(self) -> float | None:
        """The height of the support the object stands on, as the object stage recorded it."""
        height = (self.extra.get("support") or {}).get("height")
        return None if height is None else float(height)


@dataclasses.dataclass(frozen=True, eq=False)
class PhysicsRecord(_Record):
    """The exported scene (``physics``): ``scene.xml``, its USD, the background geoms, the free
    settle of the whole scene, the collision's worker processes and the config."""

    SECTION: ClassVar[str] = "physics"

    scene: str | None = None
    usd: Any = None
    up: np.ndarray | None = dataclasses.field(default=None, metadata=_MATRIX)
    background: tuple[dict, ...] = dataclasses.field(default=(), metadata=_TUPLE)
    surface: str | None = None
    scene_settle: dict | None = None
    config: dict | None = None
    collision_workers: dict | None = None
    extra: dict = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True, eq=False)
class BackgroundRecord(_Record):
    """The background (``background``): ``path`` = (G0 minus the removed Gaussians) plus the fill,
    with how many were removed and filled; per object what was removed and filled (``objects``, its
    own status words: filled, untargeted, removed, nothing_exposed, unsupported, failed, skipped)."""

    SECTION: ClassVar[str] = "background"

    path: str | None = None
    removed: int | None = None
    filled: int | None = None
    source_gaussians: int | None = None
    gaussians: int | None = None
    objects: tuple[dict, ...] = dataclasses.field(default=(), metadata=_TUPLE)
    unsupported_regions: tuple[dict, ...] = dataclasses.field(default=(), metadata=_TUPLE)
    failed_completions: tuple[dict, ...] = dataclasses.field(default=(), metadata=_TUPLE)
    extra: dict = dataclasses.field(default_factory=dict)


# section name → its record type (the other sections stay JSON: a stage's own detail record)
RECORDS: dict[str, type[_Record]] = {"frame": FrameRecord, "physics": PhysicsRecord, "background": BackgroundRecord}
LISTS: dict[str, type[_Record]] = {"instances": InstanceRecord, "objects": ObjectRecord}


def section_from_json(name: str, value: Any, where: str | Path | None = None) -> Any:
    """A manifest section as its record(s) (``RECORDS``, ``LISTS``), else the JSON as it is."""
    if value is None or isinstance(value, _Record):
        return value
    if isinstance(value, (list, tuple)) and value and isinstance(value[0], _Record):
        return tuple(value)
    if name in RECORDS:
        return RECORDS[name].from_json(value, where)
    if name in LISTS:
        if not isinstance(value, list):
            raise SceneInputError(where, name, f"expected a list, got {type(value).__name__}")
        return tuple(LISTS[name].from_json(item, where) for item in value)
    return value


def section_json(value: Any) -> Any:
    """A section's JSON form (records through ``to_json``)."""
    if isinstance(value, _Record):
        return value.to_json()
    if isinstance(value, tuple) and value and isinstance(value[0], _Record):
        return [v.to_json() for v in value]
    return plain(value)
