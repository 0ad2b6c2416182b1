"""The whole conversion: scene folder → interactive scene folder.

Stages run in the order of ``STAGES``; each takes the records of the stages before it and returns
its own (``phirie_jax.records``), which the run holds in one ``Manifest`` and writes to
``OUT/manifest.json`` after each stage:
frame (up and metres: the capture moved into a metric, +z-up world) → observe (instances)
→ objects (assets) → background (removal, inpainting targets, fill) → physics (collision,
MJCF/URDF, drop tests). The physics stage's collision starts in CoACD's worker processes as soon
as the objects exist, so it is built while the background runs (which needs only the objects'
meshes); the background runs again in the rare case that physics fails an object it removed
(``Stage``). The cameras, in the world frame, are written beside the results
(``transforms.json``) so the output folder is self-contained. A stage that fails is recorded
in the manifest (``failed_stage``) and raised as a ``StageError`` (bad input stays a
``SceneInputError``); the stages after it do not run.

Before the output folder is created or touched, the inputs and the folder are checked
(``check_inputs``; ``io.output_folder``: never into a capture, the scene folder or a folder of
files no run of ours wrote; no input inside it): a Gaussian PLY given as the scene, a missing
Gaussian PLY or cameras, a mask source or surface the scene cannot give. The run then holds the
folder's lock (one run at a time) and records each stage's status in the manifest (``stages``:
a killed run leaves its stage ``running``, so a half-converted folder never passes as converted).
A bad input found only later by a stage removes the output folder when this run created it, so an
input error never leaves a partial output behind. A run first removes the temporaries an
interrupted earlier run left in the output folder (``io.atomic``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from phirie_jax import layout, provenance
from phirie_jax.construct.background.config import BackgroundConfig
from phirie_jax.construct.objects.config import ObjectsConfig
from phirie_jax.construct.physics.config import PhysicsConfig
from phirie_jax.errors import SceneInputError, StageError
from phirie_jax.frame.config import FrameConfig, merged, scene_frame_config
from phirie_jax.frame.resolve import SceneFrame, resolve_frame, with_known_size
from phirie_jax.io.atomic import remove_temporaries
from phirie_jax.io.camera import outside_paths_allowed
from phirie_jax.io.output_folder import check_inputs_outside, check_output_folder, locked
from phirie_jax.io.scene import find_gaussians, load_scene
from phirie_jax.io.transforms_json import write_transforms_json
from phirie_jax.manifest import COMPLETE, FAILED, OUTDATED, PENDING, RUNNING, STAGE_NAMES, Manifest
from phirie_jax.observe.config import ObserveConfig
from phirie_jax.observe.masks import check_mask_source, file_mask_ids
from phirie_jax.progress import task
from phirie_jax.report.config import ReportConfig
from phirie_jax.types import SceneInput


@dataclasses.dataclass(frozen=True)
class ConvertConfig:
    """Every stage's parameters (defaults: the paper's numbers).

    Attributes:
        observe: Scene Observation.
        objects: object candidates, registration, checks and selection.
        physics: collision, physics priors, export and drop tests (also the candidates'
            settling check while ranking).
        background: removal of the objects' source Gaussians, inpainting targets and the
            plane-disk fill of what they uncover.
        report: ``report.html``, written by ``phirie convert`` after the stages.
    """

    observe: ObserveConfig = ObserveConfig()
    objects: ObjectsConfig = ObjectsConfig()
    physics: PhysicsConfig = PhysicsConfig()
    background: BackgroundConfig = BackgroundConfig()
    report: ReportConfig = ReportConfig()


@dataclasses.dataclass(frozen=True)
class Run:
    """What every stage of one conversion sees: the capture, the frame it is moved into (the
    frame stage decides it) and the scene in that frame."""

    capture: SceneInput          # as the files hold it
    out_dir: Path
    config: ConvertConfig
    frame_config: FrameConfig = FrameConfig()
    masks: str | Path | None = None
    frame: SceneFrame | None = None
    prompts: tuple = ()          # checked prompts (observe.prompts.Prompt): the mask source when given
    collision: Any = None        # physics.stage.CollisionJob started ahead of the physics stage, or None
    kept: frozenset | None = None  # ids of the objects kept when it started (the background assumes they stay)
    manifest: Manifest | None = None  # the stages' records so far (written after each stage)
    # [(frame, scene in it)]: the one list shared by every Run that dataclasses.replace derives from this one
    moved: list = dataclasses.field(default_factory=list, compare=False, repr=False)

    @property
    def scene(self) -> SceneInput:
        """The capture in the world frame: moved once per frame, and shared with the runs derived
        from this one (moving a capture's Gaussians with their spherical harmonics takes seconds)."""
        if self.frame is None:
            raise RuntimeError("the frame stage has not run")
        if not self.moved or self.moved[0][0] is not self.frame:
            self.moved[:] = [(self.frame, self.frame.apply(self.capture))]
        return self.moved[0][1]


KNOWN_SIZE_TOLERANCE = 0.01  # --known-size observes again when the scale changes by more than this
KNOWN_SIZE_ROUNDS = 3         # at most this many observations after the first


def _record_frame(run: Run) -> None:
    """The manifest's ``frame`` and the cameras in the world frame (``transforms.json``)."""
    run.manifest.set("frame", run.frame.record())
    run.manifest.write()
    if run.scene.cameras:
        write_transforms_json(run.out_dir / layout.CAMERAS, list(run.scene.cameras))


def _frame(run: Run) -> Run:
    """Up and metres per unit: given on the command line or declared by the scene folder
    (``frame.json``; ``run.frame_config`` holds both), else estimated."""
    with run.manifest.timed("frame"):
        frame = resolve_frame(run.capture, run.frame_config)
    for warning in frame.warnings:  # a frame whose cues disagree, or that rests on one, is not silent
        print(f"phirie: warning: frame: {warning}", file=sys.stderr, flush=True)
    run = dataclasses.replace(run, frame=frame)
    _record_frame(run)
    return run


def _known_size(run: Run) -> Run:
    """The frame rescaled so ``--known-size``'s instance has the given longest side."""
    ident, metres = run.frame_config.known_size_of()
    instances = run.manifest.instances()
    record = next((i for i in instances if i.id == ident), None)
    if record is None:
        raise SceneInputError(None, "--known-size", f"instance {ident} was not observed (observed: "
                              f"{', '.join(str(i.id) for i in instances) or 'none'})")
    with np.load(run.out_dir / record.points) as data:
        points = data["points"].astype(np.float64)
    run = dataclasses.replace(run, frame=with_known_size(run.frame, points, ident, metres))
    _record_frame(run)
    return run


def _observe(run: Run) -> Run:
    """Observation in the world frame; with ``--known-size`` the frame is rescaled from the named
    instance's observed size, and the scene observed again while that changes the scale (at most
    ``KNOWN_SIZE_ROUNDS`` times; the frame recorded is the one the instances were observed at)."""
    _observed(run)
    if run.frame_config.known_size is None:
        return run
    for _ in range(KNOWN_SIZE_ROUNDS):  # an instance observed at a wrong scale measures short: again
        rescaled = _known_size(run)
        if abs(rescaled.frame.scale / run.frame.scale - 1) <= KNOWN_SIZE_TOLERANCE:
            return rescaled
        _observed(rescaled)
        run = rescaled
    return run


def _observed(run: Run) -> None:
    """The instances observed in ``run.scene`` into the manifest."""
    from phirie_jax.observe.stage import observe

    m = run.manifest
    instances, record = observe(run.capture.root, run.out_dir, run.config.observe, run.masks, run.scene,
                                run.prompts, m.frame(), m.timings)
    m.set("instances", instances)
    m.set("observe", record)


def _objects(run: Run) -> Run:
    from phirie_jax.construct.objects.stage import construct_objects
    from phirie_jax.construct.physics.settling import candidate_settler

    m = run.manifest
    objects, record = construct_objects(m.instances(), m.up(), run.scene, run.out_dir, run.config.objects,
                                        candidate_settler(run.config.physics), m.observed_surface(), m.timings)
    m.set("objects", objects)
    m.set("construct", record)
    return run


def _physics(run: Run) -> Run:
    from phirie_jax.construct.physics.stage import physics

    m = run.manifest
    objects, record = physics(m.objects(), m.categories(), m.up(), m.surface_paths(), run.out_dir,
                              run.config.physics, run.collision, m.timings)
    m.set("objects", objects)
    m.set("physics", record)
    return run


def _start_collision(run: Run) -> tuple[Run, contextlib.AbstractContextManager]:
    """The kept objects' collision started in CoACD's worker processes (the physics stage takes its
    outcomes); the job terminates its workers if a stage fails meanwhile. A job that cannot start
    is left to the physics stage, which meets its error again and records it as its failure."""
    from phirie_jax.construct.physics.stage import start_collision

    run = dataclasses.replace(run, kept=_kept_ids(run.manifest))
    try:
        collision = start_collision(run.manifest.objects(), run.manifest.categories(), run.out_dir,
                                    run.config.physics)
    except Exception:  # noqa: BLE001 — the physics stage meets it again and records it as its failure
        return run, contextlib.nullcontext()
    return dataclasses.replace(run, collision=collision), collision


def _background_again(run: Run) -> tuple[str, ...]:
    """The background again when physics failed an object the background removed as kept."""
    return ("background",) if run.kept is not None and _kept_ids(run.manifest) != run.kept else ()


def _background(run: Run) -> Run:
    from phirie_jax.construct.background.stage import construct_background

    m = run.manifest
    m.set("background", construct_background(m.objects(), m.get("instances", ()), m.up(), m.support_records(),
                                             run.capture.root, run.out_dir, run.config.background, run.scene,
                                             m.timings))
    return run


def _run_stages(run: Run, selected: list[str], progress, created: Path | None) -> Run:
    """The ``selected`` stages in order (``Stage``: work started ahead, stages run again)."""
    started: set[str] = set()
    with contextlib.ExitStack() as jobs:
        for k, name in enumerate(selected):
            for later in selected[k + 1:]:   # work that can start now, to run beside this stage
                stage = STAGES[later]
                if stage.start is not None and later not in started and not set(stage.needs) & set(selected[k:]):
                    run, job = stage.start(run)
                    jobs.enter_context(job)
                    started.add(later)
            run = _run_stage(name, STAGES[name].run, run, progress, created)
            for earlier in STAGES[name].again(run):
                if earlier in selected[:k]:
                    run = _run_stage(earlier, STAGES[earlier].run, run, progress, created)
    return run


def _run_stage(name: str, stage: Callable[[Run], Run], run: Run, progress, created: Path | None) -> Run:
    """One stage, its failure recorded in the manifest; an input error removes the output folder
    this conversion created (no partial output behind)."""
    if progress is not None:
        progress(name)
    _mark(run.manifest, name, RUNNING)
    try:
        with task(name):
            run = stage(run)
    except SceneInputError as err:
        if created is not None:
            shutil.rmtree(created, ignore_errors=True)
        else:
            _failed(run.manifest, name, err)
        raise
    except Exception as err:  # noqa: BLE001 — recorded, then raised as this stage's failure
        _failed(run.manifest, name, err)
        raise StageError(name, err) from err
    _mark(run.manifest, name, COMPLETE)
    return run


def _mark(manifest: Manifest, name: str, status: str) -> None:
    """The stage's status, and the records the stages returned so far, written."""
    manifest.mark_stage(name, status)
    manifest.write()


def _kept_ids(manifest: Manifest) -> frozenset:
    return frozenset(o.id for o in manifest.kept_objects())


@dataclasses.dataclass(frozen=True)
class Stage:
    """One stage of the conversion: ``run`` takes the run and returns it.

    Attributes:
        run: the stage itself.
        needs: the stages whose outputs ``start`` reads.
        start: work begun in worker processes before the stage's turn, as soon as every stage of
            ``needs`` this run runs has run and another stage runs first (it runs meanwhile);
            returns the run (which hands the work to ``run``) and a context that ends the work
            when a stage fails before it is taken.
        again: after the stage ran, the stages that ran before it to run again (what they assumed
            no longer holds).
    """

    run: Callable[[Run], Run]
    needs: tuple[str, ...] = ()
    start: Callable[[Run], tuple[Run, contextlib.AbstractContextManager]] | None = None
    again: Callable[[Run], tuple[str, ...]] = lambda run: ()


# The stage table, in the order the stages run, each reading what the earlier ones wrote: the
# physics stage's collision is built while the background runs. ``manifest.STAGE_NAMES`` orders
# what each stage's output is made from (the background keeps the Gaussians of an object physics fails).
STAGES: dict[str, Stage] = {
    "frame": Stage(_frame), "observe": Stage(_observe), "objects": Stage(_objects),
    "background": Stage(_background),
    "physics": Stage(_physics, needs=("frame", "objects"), start=_start_collision, again=_background_again)}


# What io.scene reads cameras from, to tell a lone PLY's folder that holds them.
CAMERA_FILES = ("transforms.json", "sparse", "dslr")


def refuse_lone_ply(scene_path: Path) -> None:
    """A Gaussian PLY given as the scene has no cameras to observe with: say so, and what to pass."""
    path = Path(scene_path).absolute()
    if not (path.is_file() and path.suffix.lower() == ".ply"):
        return
    folder = path.parent
    if not any((folder / name).exists() for name in CAMERA_FILES):
        hint = f"a scene folder with cameras and images, and --gaussians {path}"
    elif find_gaussians(folder) == path:
        hint = f"its scene folder, {folder}, which holds it and the cameras"
    else:
        hint = f"its scene folder, {folder}, which holds the cameras, and --gaussians {path}"
    raise SceneInputError(path, None, f"a Gaussian PLY alone has no cameras (expected {hint})")


def check_inputs(scene: SceneInput, config: ConvertConfig, masks: str | Path | None,
                 stages: tuple[str, ...] | None, frame: FrameConfig = FrameConfig(), prompts: tuple = ()) -> None:
    """What the stages to run need from the inputs, checked before the output folder is touched;
    the errors are the ones the stages would raise later."""
    def runs(name: str) -> bool:
        return stages is None or name in stages

    scene.require_gaussians()
    scene.require_cameras()
    if runs("observe"):
        check_mask_source(scene, masks)
        if config.observe.surface_source == "mesh" and scene.surface_mesh is None:
            raise SceneInputError(scene.root, "surface", "no scan mesh (expected --surface PATH, surface.ply, "
                                  "mesh.ply or scans/mesh_aligned_0.05.ply) and surface_source is 'mesh'")
    external = config.background.targets.external
    if runs("background") and external is not None and not Path(external).is_dir():
        raise SceneInputError(external, "targets", "not a folder (expected <image stem>.png files)")
    if runs("observe"):
        _check_known_size(scene, masks, frame, prompts)


def scene_prompts(scene: SceneInput, masks: str | Path | None, given, stages: tuple[str, ...] | None
                  ) -> tuple[tuple, Path | None]:
    """(checked prompts, the prompts.json they came from or None): ``--prompt`` values (with no
    ``--masks``), else the scene folder's ``prompts.json`` when no ``--masks`` is given (with one,
    the file is left out and the run says so). Checked against the cameras before any work."""
    from phirie_jax.errors import OptionError
    from phirie_jax.observe import prompts as prompts_mod

    if stages is not None and "observe" not in stages:
        return (), None
    if given and masks is not None:
        raise OptionError("--prompt", f"and --masks {masks} are two mask sources (expected one of them)")
    if masks is not None:
        if (scene.root / prompts_mod.PROMPTS_FILE).is_file():
            print(f"phirie: note: {scene.root / prompts_mod.PROMPTS_FILE} is not used (--masks {masks} given)",
                  file=sys.stderr, flush=True)
        return (), None
    return prompts_mod.scene_prompts(scene.root, scene.require_cameras(), given)


def _check_known_size(scene: SceneInput, masks: str | Path | None, frame: FrameConfig, prompts: tuple = ()) -> None:
    """``--known-size ID=M``: with mask files (their values are the instance ids) the id is checked
    now; otherwise observation numbers the instances, and the run says at the start that the id
    is checked after it."""
    known = frame.known_size_of()
    if known is None:
        return
    ids = set(range(1, len(prompts) + 1)) if prompts else file_mask_ids(scene, masks)
    if ids is None:
        print(f"phirie: note: --known-size {frame.known_size}: instance {known[0]} is checked after observation "
              "(its instance ids are known only then)", file=sys.stderr, flush=True)
    elif known[0] not in ids:
        listed = ", ".join(map(str, sorted(ids))) or "none"
        where, what = ("--prompt", "prompts") if prompts else (scene.root / "masks", "mask files")
        raise SceneInputError(where, "--known-size", f"no instance {known[0]} in the {what} "
                              f"(their instance ids: {listed})")


def _missing_root(out_dir: Path) -> Path | None:
    """The outermost folder of ``out_dir`` that does not exist yet (what a run would create), or None."""
    missing = None
    for path in (out_dir, *out_dir.absolute().parents):
        if path.exists():
            break
        missing = path
    return missing


def _clean(out_dir: Path) -> None:
    """Remove the temporaries a killed earlier run left where the stages write."""
    for folder in layout.written_folders(out_dir):
        remove_temporaries(folder)


def _start(scene: SceneInput, out_dir: Path, selected: list[str], inputs: dict) -> Manifest:
    """The output folder's manifest (the one place a conversion reads it) with the scene it
    converts, what it is made from (``inputs``, ``provenance.inputs_record``) and the stages this
    run will run; a stage after the first of them that this run leaves alone was made from what
    this run replaces: outdated. The run holds it from here on and writes it after each stage."""
    manifest = Manifest.load_or_create(out_dir)
    manifest.set("scene", {"path": str(scene.root), "layout": scene.layout,
                           "gaussians": str(scene.gaussians_path), "cameras": len(scene.cameras)})
    manifest.set(provenance.SECTION, inputs)
    manifest.pop("failed_stage")
    status = manifest.stage_status()
    first = min(STAGE_NAMES.index(n) for n in selected)
    for name in STAGE_NAMES[first:]:
        if name in selected:
            manifest.mark_stage(name, PENDING)
        elif status[name] == COMPLETE:
            manifest.mark_stage(name, OUTDATED)
    manifest.write()
    return manifest


def _failed(manifest: Manifest, stage: str, err: BaseException) -> None:
    manifest.set("failed_stage", {"stage": stage, "error": f"{type(err).__name__}: {err}"})
    manifest.mark_stage(stage, FAILED)
    manifest.write()


def _inputs(scene: SceneInput, masks: str | Path | None, config: ConvertConfig) -> list[tuple[str, Path | None]]:
    """What the run reads, named for a message (``check_inputs_outside``)."""
    named = [("the Gaussians", scene.gaussians_path), ("the surface mesh", scene.surface_mesh),
             ("the cameras", scene.camera_source)]
    if masks not in (None, "auto", "files"):
        named.append(("the masks folder", Path(masks)))
    if config.background.targets.external is not None:
        named.append(("the inpainting targets", Path(config.background.targets.external)))
    named += [("the image", c.image_path) for c in scene.cameras]
    named += [("the mask", m) for m in scene.masks or () if m is not None]
    return named


def conversion_inputs(scene: SceneInput, config: ConvertConfig, masks: str | Path | None,
                      stages: tuple[str, ...] | None, frame: FrameConfig, prompts: tuple = ()) -> dict:
    """The ``inputs`` record of this conversion: its input files' and options' hashes. The
    collision's worker count and the workers' priority decide how fast, not what, so they are
    left out of the options."""
    physics = config.physics
    physics = dataclasses.replace(physics, workers=0, coacd=dataclasses.replace(physics.coacd, niceness=0))
    options = {"config": dataclasses.replace(config, physics=physics),
               "frame": frame, "stages": None if stages is None else sorted(stages),
               "masks": masks if masks in (None, "auto", "files") else "folder"}
    if prompts:
        options["prompts"] = [p.as_json() for p in prompts]
    extra = [masks if masks not in (None, "auto", "files") else None, config.background.targets.external]
    return provenance.inputs_record(scene, options, [Path(p) for p in extra if p is not None])


def run_convert(scene_dir: str | Path, out_dir: str | Path, config: ConvertConfig = ConvertConfig(),
                masks: str | Path | None = None, gaussians: str | Path | None = None,
                surface: str | Path | None = None, frame: FrameConfig = FrameConfig(), progress=None,
                stages: tuple[str, ...] | None = None, allow_outside_paths: bool = False, prompts=()) -> dict:
    """Run the stages of ``STAGES`` (all, or those named in ``stages``; the frame stage always
    runs) on ``scene_dir``; returns the final manifest (a dict). ``progress(stage)`` is called
    as each stage starts (and each is a ``progress.task``: shown by a display the caller
    installed). ``allow_outside_paths``: cameras may name images outside the scene folder
    (refused by default). ``prompts``: ``--prompt`` values (``IMAGE:X0,Y0,X1,Y1`` or ``IMAGE:U,V``,
    or ``observe.prompts.Prompt``s); without them and ``masks``, the scene's ``prompts.json``."""
    start = time.perf_counter()
    frame.checked()
    out_dir = Path(out_dir)
    scene_root = Path(scene_dir).parent if Path(scene_dir).is_file() else Path(scene_dir)
    refuse_lone_ply(Path(scene_dir))
    check_output_folder(out_dir, scene_root)
    with outside_paths_allowed(allow_outside_paths):
        scene = load_scene(scene_dir, gaussians=gaussians, surface=surface)
        checked, prompts_file = scene_prompts(scene, masks, tuple(prompts), stages)
        run = Run(scene, out_dir, config, merged(scene_frame_config(scene.root), frame), masks, prompts=checked)
        check_inputs(scene, config, masks, stages, run.frame_config, checked)
        check_inputs_outside(out_dir, _inputs(scene, masks, config) + [("the prompts", prompts_file)])
        inputs = conversion_inputs(scene, config, masks, stages, frame, checked)
        created = _missing_root(out_dir)
        with locked(out_dir):
            check_output_folder(out_dir, scene_root)   # as this run holds it
            _clean(out_dir)
            selected = [n for n in STAGES if stages is None or n == "frame" or n in stages]
            run = dataclasses.replace(run, manifest=_start(scene, run.out_dir, selected, inputs))
            run = _run_stages(run, selected, progress, created)
            manifest = run.manifest
            manifest.record_timing("convert", time.perf_counter() - start)
            manifest.write()
    return manifest.data
