"""``manifest.json``: the stages' records in their one serialized, schema-versioned form
(docs/architecture.md "Contracts").

The pipeline holds one ``Manifest`` per output folder: the stages' records (``phirie_jax.records``:
frame, instances, objects, physics, background), the sections that stay a stage's own JSON detail
(``scene``, ``inputs``, ``observe``, ``construct``, ``stages``, ...) and the timings. ``from_json``
and ``to_json`` are the only reader and writer of the file's content:

    manifest = Manifest.load_or_create(out_dir)
    with manifest.timed("observe"):
        instances, record = observe(...)
    manifest.set("instances", instances)
    manifest.write()
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from phirie_jax.errors import SceneInputError
from phirie_jax.io.atomic import write_text
from phirie_jax.io.jsonfile import read_json_object
from phirie_jax.layout import MANIFEST, resolve
from phirie_jax.records import (
    KEPT,
    LISTS,
    BackgroundRecord,
    FrameRecord,
    InstanceRecord,
    ObjectRecord,
    ObjectStatus,
    PhysicsRecord,
    plain,
    section_from_json,
    section_json,
)

# The schema this version writes, and those it reads (a manifest of another is refused, naming it).
SCHEMA = "phirie/1"
READS = (SCHEMA,)

# The stages of a conversion in the order their outputs build on each other (the background keeps
# the Gaussians of an object physics fails, so it follows physics; ``pipeline.STAGES`` runs it
# first, beside the collision, and again when physics fails one), as ``stages`` records them:
# ``pending`` (this run will run it), ``running`` (started, not finished: the run was killed or still
# runs), ``complete``, ``failed`` (``failed_stage`` says why) or ``outdated`` (an earlier stage ran
# again after it).
STAGE_NAMES = ("frame", "observe", "objects", "physics", "background")
PENDING, RUNNING, COMPLETE, FAILED, OUTDATED = "pending", "running", "complete", "failed", "outdated"

ACCEPTED, UNVERIFIED, REJECTED, FAILED_OBJECT = ObjectStatus
__all__ = ["KEPT", "SCHEMA", "Manifest", "ObjectStatus", "Timings"]

# The section each stage writes last (how a manifest without ``stages`` tells what ran).
LAST_WRITTEN = {"frame": "frame", "observe": "instances", "objects": "objects", "physics": "physics",
                "background": "background"}


@dataclasses.dataclass
class Elapsed:
    """Wall seconds of a finished ``Timings.timed`` block."""

    seconds: float = 0.0


class Timings:
    """The ``timings`` section ({stage: seconds}) as a run records it."""

    def __init__(self, values: dict | None = None):
        self.values: dict[str, float] = dict(values or {})
        self._timed: set[str] = set()  # timings recorded by this run (later blocks add to them)
        self._lock = threading.RLock()  # blocks timed in threads add up

    def record(self, stage: str, seconds: float) -> None:
        with self._lock:
            self.values[stage] = round(float(seconds), 6)
            self._timed.add(stage)

    @contextlib.contextmanager
    def timed(self, name: str) -> Iterator[Elapsed]:
        """Time the block into ``name`` (also when it raises). The first block of a name in this
        run replaces an earlier run's value; later blocks of the same name add to it, so a step
        inside a loop records its total. Yields an ``Elapsed`` whose ``seconds`` is this block's
        time once it ends."""
        elapsed = Elapsed()
        start = time.perf_counter()
        try:
            yield elapsed
        finally:
            elapsed.seconds = time.perf_counter() - start
            with self._lock:
                before = self.values.get(name, 0.0) if name in self._timed else 0.0
                self.record(name, before + elapsed.seconds)


class Manifest:
    """The manifest of one output folder, held in memory until ``write``: the sections in the
    order they were first set, records for the stages' sections (``records.RECORDS``/``LISTS``)."""

    def __init__(self, out_dir: str | Path, sections: dict | None = None, timings: Timings | None = None):
        self.out_dir = Path(out_dir)
        self.sections: dict[str, Any] = dict(sections or {})
        self.timings = timings if timings is not None else Timings()

    @property
    def path(self) -> Path:
        return self.out_dir / MANIFEST

    @classmethod
    def from_json(cls, out_dir: str | Path, data: dict) -> Manifest:
        """The manifest of ``data`` (the file's JSON): schema checked, each section as its record."""
        path = Path(out_dir) / MANIFEST
        if data.get("schema") not in READS:
            raise SceneInputError(path, "schema", f"{data.get('schema')!r} (expected {SCHEMA!r})")
        timings = data.get("timings", {})
        if not isinstance(timings, dict):
            raise SceneInputError(path, "timings", "expected an object {stage: seconds}")
        sections = {k: section_from_json(k, v, path) for k, v in data.items() if k not in ("schema", "timings")}
        return cls(out_dir, sections, Timings(timings))

    def to_json(self) -> dict:
        """The file's JSON: ``schema``, ``timings``, then every section (records through ``to_json``)."""
        return {"schema": SCHEMA, "timings": dict(self.timings.values),
                **{k: section_json(v) for k, v in self.sections.items()}}

    @property
    def data(self) -> dict:
        """The manifest as JSON (a copy: change it through ``set``)."""
        return self.to_json()

    @classmethod
    def load_or_create(cls, out_dir: str | Path) -> Manifest:
        """The folder's manifest when there is one (schema checked), else an empty one."""
        path = Path(out_dir) / MANIFEST
        if not path.exists():
            return cls(out_dir)
        return cls.from_json(out_dir, read_json_object(path))

    @classmethod
    def load(cls, out_dir: str | Path) -> Manifest:
        """The manifest of a converted folder; ``SceneInputError`` when it holds none."""
        if not (Path(out_dir) / MANIFEST).is_file():
            raise SceneInputError(out_dir, None, f"no {MANIFEST} (expected a phirie convert output folder)")
        return cls.load_or_create(out_dir)

    def get(self, section: str, default: Any = None) -> Any:
        """A section: its record(s) for the stages' sections, else its JSON."""
        value = self.sections.get(section)
        return default if value is None else value

    def require(self, section: str, written_by: str) -> Any:
        """A section earlier stages write; missing → an error naming them (``written_by``, e.g.
        "the observation stage")."""
        value = self.sections.get(section)
        if value is None:
            raise SceneInputError(self.path, section, f"missing (run {written_by} first: it writes the {section})")
        return value

    # --- the stages' records ---

    def frame(self) -> FrameRecord | None:
        """The scene frame (``frame``), when the frame stage recorded it."""
        return self.sections.get("frame")

    def instances(self) -> tuple[InstanceRecord, ...]:
        """The observed instances (``instances``; the observation stage writes them)."""
        return self.require("instances", "the observation stage")

    def objects(self) -> tuple[ObjectRecord, ...]:
        """Every object (``objects``; the object-construction stage writes them)."""
        return self.require("objects", "the object-construction stage")

    def kept_objects(self) -> tuple[ObjectRecord, ...]:
        """The objects that are bodies of the scene (accepted or unverified), none before the
        object stage ran."""
        return tuple(o for o in self.get("objects", ()) if o.kept)

    def accepted_objects(self) -> tuple[ObjectRecord, ...]:
        """The objects whose every check passed."""
        return tuple(o for o in self.get("objects", ()) if o.accepted)

    def physics(self) -> PhysicsRecord | None:
        return self.sections.get("physics")

    def background(self) -> BackgroundRecord | None:
        return self.sections.get("background")

    def categories(self) -> dict[int, str | None]:
        """Instance id → category (None when the observation did not name one)."""
        return {inst.id: inst.category for inst in self.get("instances", ())}

    def up(self) -> np.ndarray:
        """(3,) the scene's up, as decided once (``phirie_jax.frame``) and recorded in ``frame``.
        Folders written before the ``frame`` section keep it under ``construct.gravity``; +z
        when no stage decided one."""
        frame = self.frame()
        if frame is not None and frame.up is not None:
            return frame.up_vector()
        up = ((self.get("construct") or {}).get("gravity") or {}).get("up")
        return np.asarray(up if up is not None else (0.0, 0.0, 1.0), np.float64)

    def capture_to_world(self) -> np.ndarray | None:
        """(4, 4) the Sim(3) from the capture's frame to the scene's (``frame``), when recorded."""
        frame = self.frame()
        return None if frame is None else frame.capture_to_world

    def observed_surface(self) -> Path | None:
        """The surface the observation stage lifted onto (scan mesh or splat-derived), as a path
        to open; None when it recorded none."""
        path = ((self.get("observe") or {}).get("surface") or {}).get("path")
        return resolve(self.out_dir, path) if path else None

    def surface_paths(self) -> list[str]:
        """The scene surfaces earlier stages recorded, as written (the object stage's choice first,
        then the observation stage's)."""
        return [p for p in ((self.get("construct") or {}).get("surface"),
                            ((self.get("observe") or {}).get("surface") or {}).get("path")) if p]

    def support_records(self) -> dict[int, dict]:
        """Object id → the record of the support it stands on (``observe.support.Support.as_record``),
        as observation recorded it with the instance (older folders: as the object stage did)."""
        found = {int(s["id"]): {"normal": [0.0, 0.0, 1.0], "hits": 0, **s}
                 for s in (self.get("construct") or {}).get("supports") or [] if s.get("height") is not None}
        found.update({int(i.id): i.support for i in self.get("instances", ()) if i.support})
        return found

    # --- which stages finished ---

    def stage_status(self) -> dict[str, str]:
        """Stage name → its status (``STAGE_NAMES``; "not run" for a stage never started). A folder
        written without ``stages`` (by an earlier version, or by a stage called on its own): a stage
        is complete when the section it writes last is there and it is not the ``failed_stage``."""
        recorded = self.sections.get("stages")
        if isinstance(recorded, dict):
            return {name: str(recorded.get(name, "not run")) for name in STAGE_NAMES}
        failed = (self.sections.get("failed_stage") or {}).get("stage")
        return {name: FAILED if name == failed else COMPLETE if self.sections.get(section) is not None else "not run"
                for name, section in LAST_WRITTEN.items()}

    def mark_stage(self, name: str, status: str) -> None:
        if name not in STAGE_NAMES:
            raise ValueError(f"unknown stage {name!r}")
        stages = self.sections.get("stages")
        self.sections["stages"] = {**(stages if isinstance(stages, dict) else {}), name: status}

    def unfinished(self, stages: tuple[str, ...] = STAGE_NAMES) -> dict[str, str]:
        """The stages of ``stages`` that are not complete, with their status."""
        status = self.stage_status()
        return {name: status[name] for name in stages if status[name] != COMPLETE}

    def require_complete(self, stages: tuple[str, ...], needed_by: str) -> None:
        """``SceneInputError`` naming the first of ``stages`` that did not complete (``needed_by``
        says what needs them, e.g. "the drop tests")."""
        unfinished = self.unfinished(stages)
        if unfinished:
            name, status = next(iter(unfinished.items()))
            raise SceneInputError(self.path, "stages", f"the {name} stage {describe_status(status)} (expected a "
                                  f"complete conversion for {needed_by}: run phirie convert again)")

    def set(self, section: str, value: Any) -> None:
        """Replace one section: records as they are, JSON values (a stage's detail, or a record's
        JSON form) read as ``records.section_from_json`` reads the file (``schema`` and ``timings``
        have their own methods)."""
        if section in ("schema", "timings"):
            raise ValueError(f"section {section!r} is managed by the manifest itself")
        self.sections[section] = section_from_json(section, _records_or_plain(value), self.path)

    def pop(self, section: str) -> Any:
        return self.sections.pop(section, None)

    def upsert(self, section: str, items: list, key: str = "id") -> None:
        """Add items (records, or JSON objects) to a list section, replacing those with the same
        ``key``; sorted by it."""
        def key_of(item):
            return item[key] if isinstance(item, dict) else getattr(item, key)

        current = {key_of(item): item for item in self.sections.get(section) or []}
        for item in items:
            current[key_of(item)] = section_from_json(section, [plain(item)], self.path)[0] if isinstance(item, dict) \
                else item
        value = [current[k] for k in sorted(current)]
        self.sections[section] = tuple(value) if section in LISTS else value

    def record_timing(self, stage: str, seconds: float) -> None:
        self.timings.record(stage, seconds)

    def timed(self, name: str):
        """``Timings.timed`` of this manifest's timings."""
        return self.timings.timed(name)

    def write(self) -> Path:
        """Write ``manifest.json`` atomically (never half-written) and return its path."""
        write_text(self.path, json.dumps(self.to_json(), indent=2, allow_nan=False) + "\n")
        return self.path


def _records_or_plain(value: Any) -> Any:
    """Records (or a sequence of them) as they are; anything else as JSON values."""
    if isinstance(value, (list, tuple)) and value and hasattr(value[0], "to_json"):
        return tuple(value)
    return value if hasattr(value, "to_json") else plain(value)


def describe_status(status: str) -> str:
    """A stage's status as the end of a sentence ("the physics stage ...")."""
    return {RUNNING: "did not finish (the run was killed, or is still running)", FAILED: "failed",
            PENDING: "did not start (an earlier stage did not finish)", OUTDATED: "is outdated (an earlier "
            "stage ran again after it)", "not run": "has not run", "unknown": "did not finish (no record of "
            "the conversion's end)"}.get(status, f"is {status}")


def to_dict(config) -> dict:
    """A config as plain JSON-ready values (nested configs included)."""
    return dataclasses.asdict(config)
