"""``phirie convert-many``: many scenes converted as Ray tasks, one output folder each.

The driver names the scenes (``scene_names``: their folder names, made unique), checks the root
and every scene's output folder before any work (``io.output_folder``'s rules), connects to Ray
(``connect``: a local instance by default, or a running cluster), checks what the tasks ask for
against the cluster's resources and submits one task per scene (``scene_task.convert_scene``),
holding the root's lock (one ``convert-many`` per root at a time: an existing root is taken
before Ray starts, a new one is created once the resources are checked).
Each task holds ``cpus`` CPUs, a GPU when the cluster has one, and the ``resources`` asked for;
it runs in a fresh worker process (``max_calls=1``: its peak memory is its own, no state is
shared between scenes) and is retried up to ``retries`` times when its worker dies or it raises
``TransientSceneError``; a scene that still fails is recorded with its reason. As each scene
ends, ``ROOT/summary.json`` is written again (atomically), so a killed driver leaves the
scenes that ended recorded.

Ray is an optional extra: ``import_ray`` says how to install it when it is missing.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import logging
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from phirie_jax import layout
from phirie_jax.cluster.scene_task import FAILED, SceneJob, TransientSceneError, convert_scene, manifest_facts
from phirie_jax.errors import OptionError, SceneInputError
from phirie_jax.io.atomic import write_text
from phirie_jax.io.output_folder import capture_inputs, check_output_folder, locked

INSTALL = "pip install 'phirie_jax[cluster]'"
SUMMARY = "summary.json"
SUMMARY_SCHEMA = "phirie-many/1"
LOCAL = "local"


def import_ray():
    """The ``ray`` module; ``OptionError`` saying how to install it when it is missing."""
    try:
        import ray
    except ImportError:
        raise OptionError("phirie convert-many", f"needs Ray (expected it installed: {INSTALL})") from None
    return ray


@dataclasses.dataclass(frozen=True)
class Placement:
    """Where and how the tasks run.

    Attributes:
        address: None for a local Ray instance started here, else a running cluster's address
            (``auto``, ``HOST:PORT`` or ``ray://HOST:PORT``).
        workers: the local instance's CPUs, i.e. scenes at once with one CPU a scene (None: every
            core of this machine); a running cluster has its own.
        cpus: CPUs each scene's task holds (its collision's worker processes).
        gpus: GPUs each scene's task holds; None: one when the cluster has a GPU, else none.
        resources: custom Ray resources each task holds (e.g. {"bigmem": 1}); the cluster must
            have them.
        retries: attempts after the first, for a task whose worker died or that failed transiently.
    """

    address: str | None = None
    workers: int | None = None
    cpus: int = 1
    gpus: float | None = None
    resources: dict[str, float] = dataclasses.field(default_factory=dict)
    retries: int = 2


def scene_names(scenes: Sequence[Path]) -> list[str]:
    """Each scene's output folder name: its folder's name (a Gaussian PLY given as the scene: the
    folder holding it). Scenes of the same name take as many parent folders as tell them apart
    (``a-scene``, ``b-scene``); scenes still alike get ``-2``, ``-3`` in the order given."""
    roots = [Path(os.path.abspath(s)) for s in scenes]
    roots = [r.parent if r.suffix.lower() == ".ply" else r for r in roots]
    parts = [[p for p in reversed(r.parts) if p not in ("/", "")] or ["scene"] for r in roots]
    depth = [1] * len(roots)
    while True:
        names = ["-".join(reversed(p[:d])) for p, d in zip(parts, depth)]
        counts = collections.Counter(names)
        grow = [k for k, n in enumerate(names) if counts[n] > 1 and depth[k] < len(parts[k])]
        if not grow:
            break
        for k in grow:
            depth[k] += 1
    seen: collections.Counter = collections.Counter()
    unique = []
    for name in names:
        seen[name] += 1
        unique.append(name if seen[name] == 1 else f"{name}-{seen[name]}")
    return unique


def check_root(root: Path, scenes: Sequence[Path], names: Sequence[str]) -> None:
    """Refuse a root that is a file, a capture or one conversion's output, and any scene whose
    output folder ``ROOT/<name>`` a conversion must not write into; nothing is written."""
    if root.exists() and not root.is_dir():
        raise OptionError("--out", "is a file (expected a folder to hold one output folder per scene)", str(root))
    if root.is_dir():
        found = capture_inputs(root)
        if found:
            raise OptionError("--out", f"holds a capture's inputs ({', '.join(found)}) (expected a folder to hold "
                              "one output folder per scene)", str(root))
        if (root / layout.MANIFEST).is_file():
            raise OptionError("--out", f"holds a {layout.MANIFEST}: one conversion's output (expected a folder to "
                              "hold one output folder per scene)", str(root))
    for scene, name in zip(scenes, names):
        scene_root = Path(scene).parent if Path(scene).is_file() else Path(scene)
        check_output_folder(root / name, scene_root)


def connect(ray, placement: Placement) -> None:
    """``ray.init``: a local instance (``placement.workers`` CPUs, no dashboard, quiet logs, no usage
    statistics sent unless ``RAY_USAGE_STATS_ENABLED`` says otherwise) or the cluster at
    ``placement.address``."""
    quiet = {"include_dashboard": False, "log_to_driver": False, "logging_level": logging.ERROR}
    if placement.address is None:
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")   # a run on this machine reports to no one
        ray.init(address=LOCAL, num_cpus=placement.workers or os.cpu_count() or 1, **quiet)
    else:
        try:
            ray.init(address=placement.address, **quiet)
        except (ConnectionError, ValueError, RuntimeError) as err:
            raise OptionError("--address", f"no Ray cluster could be reached ({' '.join(str(err).split())}) "
                              "(expected a running cluster: ray start --head, or auto for the one on this "
                              "machine)", placement.address) from None


def task_options(ray, placement: Placement) -> dict:
    """The tasks' Ray options: CPUs, a GPU when the cluster has one, the custom resources (each
    checked against the cluster's), retries, a fresh worker process per task."""
    available = ray.cluster_resources()
    for name, amount in placement.resources.items():
        if available.get(name, 0) < amount:
            have = ", ".join(sorted(k for k in available if not k.startswith("node:"))) or "none"
            raise OptionError("--resources", f"the cluster has {available.get(name, 0):g} of {name!r} (expected at "
                              f"least {amount:g}; it has: {have})", f"{name}={amount:g}")
    if available.get("CPU", 0) < placement.cpus:
        raise OptionError("--cpus-per-scene", f"the cluster has {available.get('CPU', 0):g} CPUs (expected at "
                          f"least {placement.cpus})", str(placement.cpus))
    gpus = placement.gpus if placement.gpus is not None else (1.0 if available.get("GPU", 0) >= 1 else 0.0)
    if gpus > available.get("GPU", 0):
        raise OptionError("--gpus-per-scene", f"the cluster has {available.get('GPU', 0):g} GPUs", f"{gpus:g}")
    options = {"num_cpus": placement.cpus, "num_gpus": gpus, "max_retries": placement.retries,
               "retry_exceptions": [TransientSceneError]}
    if placement.resources:
        options["resources"] = dict(placement.resources)
    if 0 < gpus < 1:   # tasks share a GPU: JAX must not take most of its memory up front
        options["runtime_env"] = {"env_vars": {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}}
    return options


def _lost(ray, job: SceneJob, err: BaseException, attempts: int) -> dict:
    """The record of a scene whose task raised (a transient failure every attempt met, or a worker
    that died every time): failed, with the last reason."""
    cause = err
    if isinstance(err, ray.exceptions.RayTaskError):
        cause = err.cause if getattr(err, "cause", None) is not None else err
    if isinstance(cause, TransientSceneError):
        reason = f"{cause} (after {attempts} attempts)"
    elif isinstance(cause, ray.exceptions.WorkerCrashedError):
        reason = f"its worker process died in each of {attempts} attempts"
    elif isinstance(cause, ray.exceptions.OutOfMemoryError):
        reason = f"Ray stopped its worker for lack of memory in each of {attempts} attempts"
    elif isinstance(cause, ray.exceptions.TaskCancelledError):
        reason = "cancelled"
    else:
        reason = f"{type(cause).__name__}: {' '.join(str(cause).split())[:500]}"
    return {"name": job.name, "scene": str(job.scene), "out": str(job.out), "status": FAILED, "reason": reason,
            **{k: v for k, v in manifest_facts(job.out).items() if k != "failed_stage"},
            "seconds": None, "peak_memory_mb": None, "peak_memory_children_mb": None}


def write_summary(root: Path, records: list[dict], meta: dict) -> Path:
    """``ROOT/summary.json`` (atomically): the run's settings and one record per scene, in the
    order given (scenes not ended yet: ``pending``)."""
    import json

    counts = collections.Counter(r["status"] for r in records)
    data = {"schema": SUMMARY_SCHEMA, **meta, "counts": dict(sorted(counts.items())), "scenes": records}
    path = root / SUMMARY
    write_text(path, json.dumps(data, indent=2, allow_nan=False) + "\n")
    return path


def convert_many(scenes: Sequence[Path], root: Path, job: SceneJob, placement: Placement = Placement(),
                 on_start: Callable[[dict], None] | None = None,
                 on_end: Callable[[dict], None] | None = None) -> dict:
    """Convert every scene into ``ROOT/<name>`` (module docstring); ``job`` holds the options every
    scene shares (its name, scene and out are set per scene). ``on_start(meta)`` is called once the
    tasks are submitted (``meta``: where they run), ``on_end(record)`` as each scene ends. Returns
    the summary (what ``summary.json`` holds)."""
    ray = import_ray()
    start = time.perf_counter()
    root = Path(root)
    scenes = [Path(s) for s in scenes]
    if not scenes:
        raise OptionError("convert-many", "no scene given (expected one or more scene folders)")
    if len({os.path.realpath(s) for s in scenes}) < len(scenes):
        twice = next(s for k, s in enumerate(scenes) if os.path.realpath(s) in map(os.path.realpath, scenes[:k]))
        raise SceneInputError(twice, None, "given twice (expected each scene once)")
    names = scene_names(scenes)
    check_root(root, scenes, names)
    jobs = [dataclasses.replace(job, name=n, scene=s.absolute(), out=(root / n).absolute(), cpus=placement.cpus)
            for n, s in zip(names, scenes)]
    records = [{"name": j.name, "scene": str(j.scene), "out": str(j.out), "status": "pending"} for j in jobs]
    with contextlib.ExitStack() as held:
        taken = root.is_dir()
        if taken:   # an existing root that another run holds is refused before Ray starts
            held.enter_context(locked(root))
        connect(ray, placement)
        pending: dict = {}
        try:
            options = task_options(ray, placement)   # refused before a new root is created
            meta = {"root": str(root.absolute()), "address": placement.address or LOCAL,
                    "cluster": {k: v for k, v in ray.cluster_resources().items() if not k.startswith("node:")},
                    "task": {k: options[k] for k in ("num_cpus", "num_gpus", "max_retries")} | {
                        "resources": options.get("resources", {})}}
            if not taken:
                held.enter_context(locked(root))
            remote = ray.remote(max_calls=1)(convert_scene)   # a fresh worker process per scene
            pending = {remote.options(name=f"phirie convert {j.name}", **options).remote(j): k
                       for k, j in enumerate(jobs)}
            write_summary(root, records, {**meta, "seconds": None})
            if on_start is not None:
                on_start(meta)
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                k = pending.pop(done[0])
                try:
                    records[k] = ray.get(done[0])
                except Exception as err:  # noqa: BLE001 — a task that raised after its retries: recorded
                    records[k] = _lost(ray, jobs[k], err, placement.retries + 1)
                write_summary(root, records, {**meta, "seconds": None})
                if on_end is not None:
                    on_end(records[k])
            seconds = round(time.perf_counter() - start, 2)
            write_summary(root, records, {**meta, "seconds": seconds})
        except BaseException:
            for ref in pending:   # interrupted: the scenes not ended are stopped (their folders say so)
                ray.cancel(ref, force=True)
            raise
        finally:
            ray.shutdown()
    counts = collections.Counter(r["status"] for r in records)
    return {"schema": SUMMARY_SCHEMA, **meta, "seconds": seconds, "counts": dict(sorted(counts.items())),
            "scenes": records}
