"""One scene's conversion, as ``phirie convert-many`` runs it in a Ray worker process.

``convert_scene(job)`` is the task: it converts ``job.scene`` into ``job.out`` with
``pipeline.run_convert`` (the output folder's rules and lock, the stages' statuses, atomic
writes: as ``phirie convert``), writes ``report.html`` when the config asks for it, and returns
the scene's ``SceneResult`` record. It never raises for a scene that failed for a reason another
attempt would meet again (bad input, a stage that failed on this scene): the record says
``failed`` and why, and the other scenes go on. A failure another attempt may not meet (memory
ran out, a worker pool or a native library was killed, an I/O error the system calls temporary)
is raised as ``TransientSceneError``, which the driver lets Ray retry a bounded number of times;
a worker process that dies is retried by Ray the same way.

A folder whose conversion completed from the same inputs with the same options
(``provenance.up_to_date``) is not converted again: the record says ``skipped`` and is read from
its manifest. A folder left by a killed attempt holds a stale lock, which ``run_convert`` takes
over; the record names the process it took over from (``took_over``).

The peak memory is the task's process's and its children's (``resource.getrusage`` maximum
resident set): the driver runs each task in a fresh worker process (``max_calls=1``), so it is
this scene's.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import resource
import socket
import time
from pathlib import Path

from phirie_jax import layout, provenance
from phirie_jax.errors import ConfigValueError, NativeLibraryError, OptionError, SceneInputError, StageError
from phirie_jax.frame.config import FrameConfig
from phirie_jax.manifest import Manifest, ObjectStatus
from phirie_jax.pipeline import ConvertConfig

CONVERTED, SKIPPED, FAILED = "converted", "skipped", "failed"
# errno values of failures the system itself calls temporary (or a network filesystem's)
TRANSIENT_ERRNO = {errno.EAGAIN, errno.EBUSY, errno.EINTR, errno.EIO, errno.ENOMEM, errno.ESTALE, errno.ETIMEDOUT}


class TransientSceneError(RuntimeError):
    """A scene's conversion failed in a way another attempt may not meet (module docstring); Ray
    retries the task on it. The message is the failure's one line."""


@dataclasses.dataclass(frozen=True)
class SceneJob:
    """What one task converts, and how.

    Attributes:
        name: the scene's name among those converted (its folder under the root).
        scene: the scene folder (or its Gaussian PLY), as the workers see it.
        out: the output folder, ``ROOT/<name>``.
        config: every stage's parameters (as ``phirie convert --config...``).
        masks: the mask source (``--masks``), or None for the scene's own.
        frame: the frame options shared by the scenes (``--up``, ``--metric`` ...).
        allow_outside_paths: cameras may name images outside the scene folder.
        cpus: CPUs the task holds: the collision's worker processes when ``physics.workers`` is 0
            (every core otherwise, whatever the other tasks on the machine hold).
    """

    name: str
    scene: Path
    out: Path
    config: ConvertConfig = ConvertConfig()
    masks: str | None = None
    frame: FrameConfig = FrameConfig()
    allow_outside_paths: bool = False
    cpus: int = 1


def _peak_memory_mb() -> tuple[float, float]:
    """(this process's, its largest waited-for child's) maximum resident set in MiB (Linux: KiB)."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return round(own / 1024, 1), round(children / 1024, 1)


def is_transient(err: BaseException) -> bool:
    """Whether another attempt may not meet ``err`` (memory, a killed process, a temporary I/O
    error); bad input and a stage's own verdict are not."""
    from concurrent.futures.process import BrokenProcessPool

    cause = err.cause if isinstance(err, StageError) else err
    if isinstance(cause, (SceneInputError, OptionError, ConfigValueError)):
        return False
    if isinstance(cause, (MemoryError, BrokenProcessPool, TimeoutError, ConnectionError)):
        return True
    if isinstance(cause, NativeLibraryError):
        return cause.signal == "SIGKILL"   # killed from outside (the kernel's OOM killer); a crash is not
    if isinstance(cause, OSError):
        return cause.errno in TRANSIENT_ERRNO
    return "RESOURCE_EXHAUSTED" in str(cause)   # an accelerator's memory ran out (XLA's status)


def one_line(err: BaseException) -> str:
    text = " ".join(str(err).split())
    return text if isinstance(err, (StageError, SceneInputError, OptionError)) else f"{type(err).__name__}: {text}"


def _stale_holder(out: Path) -> int | None:
    """The process id in a lock file a killed run left in ``out`` (None when there is none, or its
    holder still runs: then ``run_convert`` refuses the folder and says whose it is)."""
    from phirie_jax.io.output_folder import running_holder

    path = out / layout.LOCK
    try:
        pid = int(json.loads(path.read_text(encoding="utf-8"))["pid"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return None if running_holder(out) else pid


def _up_to_date(job: SceneJob) -> bool:
    """Whether ``job.out`` holds a complete conversion of the same inputs with the same options.
    The scene is loaded (and its files hashed) only when the folder's stages are all complete."""
    from phirie_jax.io.camera import outside_paths_allowed
    from phirie_jax.io.scene import load_scene
    from phirie_jax.pipeline import conversion_inputs

    if not (job.out / layout.MANIFEST).is_file():
        return False
    manifest = Manifest.load_or_create(job.out)
    if manifest.unfinished() or not isinstance(manifest.get(provenance.SECTION), dict):
        return False
    with outside_paths_allowed(job.allow_outside_paths):
        scene = load_scene(job.scene)
    return provenance.up_to_date(job.out, conversion_inputs(scene, job.config, job.masks, None, job.frame))


def _config(job: SceneJob) -> ConvertConfig:
    """The job's config with the collision built in the task's CPUs (when left to one per core)."""
    physics = job.config.physics
    if physics.workers:
        return job.config
    return dataclasses.replace(job.config, physics=dataclasses.replace(physics, workers=max(1, job.cpus)))


def _write_report(job: SceneJob) -> str | None:
    """``report.html`` when the config asks for it; why it was not written, or None."""
    from phirie_jax.io.output_folder import locked
    from phirie_jax.report.page import write_report

    if not job.config.report.enabled:
        return None
    try:
        with locked(job.out):
            write_report(job.out, job.config.report)
    except Exception as err:  # noqa: BLE001 — the conversion stands; its report is a view of it
        return one_line(err)
    return None


def convert_scene(job: SceneJob) -> dict:
    """The task (module docstring): the scene's ``SceneResult`` record, JSON-ready."""
    from phirie_jax.pipeline import run_convert

    start = time.perf_counter()
    record = {"name": job.name, "scene": str(job.scene), "out": str(job.out), "host": socket.gethostname(),
              "pid": os.getpid()}
    try:
        if _up_to_date(job):
            return finished(record, job.out, SKIPPED, None, start)
        stale = _stale_holder(job.out)
        if stale is not None:
            record["took_over"] = stale
        run_convert(job.scene, job.out, _config(job), masks=job.masks, frame=job.frame,
                    allow_outside_paths=job.allow_outside_paths)
    except Exception as err:  # noqa: BLE001 — recorded (or retried), the other scenes go on
        if is_transient(err):
            raise TransientSceneError(one_line(err)) from err
        return finished(record, job.out, FAILED, one_line(err), start)
    report = _write_report(job)
    if report is not None:
        record["report"] = f"not written: {report}"
    return finished(record, job.out, CONVERTED, None, start)


def finished(record: dict, out: Path, status: str, reason: str | None, start: float) -> dict:
    """``record`` with the scene's status, reason, what its manifest says (``manifest_facts``),
    the task's time and peak memory."""
    own, children = _peak_memory_mb()
    facts = manifest_facts(out)
    if status == FAILED and reason is None:
        reason = facts.pop("failed_stage", None)
    facts.pop("failed_stage", None)
    return {**record, "status": status, "reason": reason, **facts,
            "seconds": round(time.perf_counter() - start, 2), "peak_memory_mb": own,
            "peak_memory_children_mb": children}


def manifest_facts(out: Path) -> dict:
    """What the summary shows of a converted folder: objects by status, drop tests, background
    figures, frame source, the conversion's own seconds (empty values when it has no manifest)."""
    facts: dict = {"objects": None, "drop_tests": None, "background": None, "frame": None, "convert_seconds": None}
    try:
        manifest = Manifest.load_or_create(out) if (Path(out) / layout.MANIFEST).is_file() else Manifest(out)
    except (SceneInputError, OSError):
        manifest = Manifest(out)
    objects = manifest.get("objects")
    if objects is not None:
        facts["objects"] = {s: sum(o.status == s for o in objects) for s in ObjectStatus}
        drops = [o.drop_test for o in objects if o.drop_test]
        facts["drop_tests"] = {"tested": len(drops), "stable": sum(bool(d.get("stable")) for d in drops),
                               "not_measured": sum(bool(d.get("error")) for d in drops)}
    background = manifest.background()
    if background is not None:
        facts["background"] = {k: getattr(background, k) for k in ("source_gaussians", "gaussians", "removed", "filled")}
    frame = manifest.frame()
    if frame is not None:
        facts["frame"] = {"scale": frame.scale, "scale_source": frame.scale_source, "up_source": frame.up_source}
    facts["convert_seconds"] = manifest.timings.values.get("convert")
    failed = manifest.get("failed_stage")
    if failed:
        facts["failed_stage"] = f"stage {failed.get('stage')} failed: {failed.get('error')}"
    return facts
