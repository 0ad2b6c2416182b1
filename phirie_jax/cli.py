"""The ``phirie`` command.

Subcommands are plain functions; tyro turns their typed, documented arguments into
the command line (and nested config dataclasses into ``--stage.field`` options), so
the CLI, the configs and their documentation never drift apart.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import json
import sys
from pathlib import Path
from typing import Annotated, Literal

import tyro

from phirie_jax.capture.command import capture
from phirie_jax.cluster import ScenesFailed
from phirie_jax.compile_cache import use_compile_cache
from phirie_jax.construct.physics.config import PhysicsConfig
from phirie_jax.errors import ConfigValueError, OptionError, SceneInputError, StageError
from phirie_jax.frame.config import FrameConfig
from phirie_jax.io.camera import outside_paths_allowed
from phirie_jax.manifest import Manifest
from phirie_jax.observe.config import ObserveConfig
from phirie_jax.pipeline import ConvertConfig
from phirie_jax.ranges import (
    AT_LEAST_ONE,
    FRACTION,
    NON_NEGATIVE,
    Each,
    check_option,
    check_options,
    deferred_checks,
    resume_checks,
)
from phirie_jax.report.config import ReportConfig
from phirie_jax.view.config import ViewConfig

Scene = Annotated[Path, tyro.conf.Positional]
Prompts = Annotated[tuple[str, ...], tyro.conf.UseAppendAction]   # --prompt A --prompt B: both kept


def info(scene: Scene, gaussians: Path | None = None, surface: Path | None = None,
         json_out: Annotated[bool, tyro.conf.arg(name="json")] = False, allow_outside_paths: bool = False) -> None:
    """Report what a scene folder (or a Gaussian PLY) holds: layout, Gaussians, cameras,
    images, surface mesh, masks, candidates and scene bounds; of a `phirie convert` output
    folder: its frame, each object (status, candidate, drop test, mass, parts), the background,
    the files written and the stages' times.

    Args:
        scene: a scene folder (COLMAP, nerfstudio or ScanNet++ layout), a Gaussian PLY, or a
            converted folder (it holds manifest.json).
        gaussians: Gaussian PLY to use instead of the one found in the folder.
        surface: surface mesh to use instead of the one found in the folder.
        json_out: print the facts as JSON instead of a table.
        allow_outside_paths: read images the cameras name outside the scene folder (refused by default).
    """
    from phirie_jax.info import converted_facts, is_converted, scene_facts
    from phirie_jax.io.scene import load_scene

    if is_converted(scene):
        facts = converted_facts(scene)
        if json_out:
            print(json.dumps(facts, indent=2))
        else:
            _print_converted(facts)
        return
    with outside_paths_allowed(allow_outside_paths):
        facts = scene_facts(load_scene(scene, gaussians=gaussians, surface=surface))
    if json_out:
        print(json.dumps(facts, indent=2))
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"phirie info: {facts['root']}", show_header=False)
    table.add_column("what", style="bold")
    table.add_column("value")
    for key, value in facts.items():
        if key == "root":
            continue
        if isinstance(value, dict):
            value = "\n".join(f"{k}: {v}" for k, v in value.items())
        table.add_row(key, "—" if value is None else str(value))
    Console().print(table)


def _print_converted(facts: dict) -> None:
    """``phirie info`` of a converted folder: a summary table, then one row per object."""
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    from phirie_jax.info import STATUS_COLOURS, status_text

    console = Console()
    table = Table(title=f"phirie info: {facts['root']} ({facts['state']})", show_header=False)
    table.add_column("what", style="bold")
    table.add_column("value")
    for key in ("scene", "frame", "outcome", "background", "files", "timings_s"):
        value = facts.get(key)
        if isinstance(value, dict):
            value = "\n".join(f"{k}: {v}" for k, v in value.items())
        elif isinstance(value, list):
            value = "\n".join(map(str, value))
        table.add_row(key, "—" if value in (None, "") else str(value))
    console.print(table)
    objects = Table(title="objects")
    for column in ("id", "status", "candidate", "drop test", "mass (kg)", "friction", "parts", "reason"):
        objects.add_column(column)
    for row in facts["objects"]:
        cells = ["—" if row[k] is None else str(row[k]) for k in
                 ("id", "status", "candidate", "drop_test", "mass", "friction", "parts", "reason")]
        words = status_text(row["status"], row["failed_checks"], row.get("mounted", False))
        cells[1] = f"[{STATUS_COLOURS.get(row['status'], 'default')}]{escape(words)}[/]"
        if row.get("mass") is not None:
            cells[4] = f"{row['mass']:.3g}" + (f" ({escape(row['mass_source'])})" if row.get("mass_source") else "")
        objects.add_row(*cells)
    console.print(objects)


def synth(out: Annotated[Path, tyro.conf.Positional], seed: int = 0,
          preset: Literal["tiny", "default", "large", "crowded"] = "default", fitted: bool = False,
          fit_steps: int | None = None, marker: float = 0.0) -> None:
    """Write a procedural tabletop scene with ground truth, laid out like a real capture
    (INRIA PLY, transforms.json and COLMAP text, images, 16-bit instance masks, surface mesh, gt/).

    Args:
        out: output scene folder.
        seed: random seed; the same seed and preset give the same files.
        preset: tiny (tests, seconds), default (the demo), large (benchmarks), crowded (30 objects on a 2 m table).
        fitted: replace the ideal Gaussians with a 3DGS fit of the rendered images (random
            initialization, Adam, densification), like a real capture's; the ideal set is kept in
            gt/ideal/ and how it was fitted in gt/fit.json.
        fit_steps: with --fitted, the number of Adam steps (default: the preset's, FIT_PRESETS:
            tiny 300, under 2 minutes on a CPU; default 3,600, about 2 minutes on a GPU and
            hours on a CPU).
        marker: print an ArUco marker (DICT_4X4_50, id 0) whose black square is this many metres
            on the table top (0: none); its corners go to gt/markers.json, so
            ``--marker-size`` is tested with truth.
    """

    check_option("--seed", seed, NON_NEGATIVE)
    check_option("--fit-steps", fit_steps, AT_LEAST_ONE)
    if not (marker >= 0 and marker < float("inf")):
        raise OptionError("--marker", f"{marker} (expected the marker's side in metres, or 0 for none)")
    if marker and fitted:
        raise SceneInputError(None, "--marker", "given with --fitted (a marker is printed on ideal scenes only)")
    from rich.console import Console

    from phirie_jax.io.output_folder import check_scene_target
    from phirie_jax.synthetic.scene import TRUTH_OBJECTS

    check_scene_target(out, TRUTH_OBJECTS)

    from phirie_jax.synthetic import synthesize

    if fit_steps is not None and not fitted:
        raise SceneInputError(None, "--fit-steps", "given without --fitted")
    if not fitted:
        with Console().status(f"synthesizing {preset} scene (seed {seed})"):
            scene = synthesize(out, preset=preset, seed=seed, marker=marker)
        print(f"wrote {out}: {len(scene.objects)} objects, {scene.capture.data.num:,} Gaussians, "
              f"{len(scene.cameras)} cameras")
    else:
        from phirie_jax.synthetic.fitted import fit_config_for, synthesize_fitted

        config = fit_config_for(preset, fit_steps)
        with Console().status(f"synthesizing {preset} scene (seed {seed}) and fitting Gaussians to its images "
                              f"({config.steps} steps)"):
            scene, result = synthesize_fitted(out, preset, seed, config)
        r = result.record
        print(f"wrote {out}: {len(scene.objects)} objects, {r['gaussians']:,} fitted Gaussians "
              f"({scene.capture.data.num:,} ideal ones in gt/ideal/), {len(scene.cameras)} cameras; "
              f"fitted in {r['wall_s']:.0f} s to train PSNR {r['train_psnr']:.2f} dB (gt/fit.json)")


def render(scene: Scene, out: Path, camera: int = 0, width: int | None = None,
           gaussians: Path | None = None,
           background: tuple[float, float, float] = (0.0, 0.0, 0.0), allow_outside_paths: bool = False) -> None:
    """Render a scene's Gaussians from one of its cameras to a PNG.

    Args:
        scene: a scene folder.
        out: output image (.png).
        camera: camera index K (the K-th image in name order).
        width: output width in pixels (height follows the camera's aspect); default: the camera's.
        gaussians: Gaussian PLY to use instead of the one found in the folder.
        background: background colour, rgb in [0, 1].
        allow_outside_paths: accept cameras that name images outside the scene folder (refused by default).
    """
    check_option("--width", width, AT_LEAST_ONE)
    check_option("--background", background, Each(FRACTION, count=3))
    import numpy as np

    from phirie_jax.errors import SceneInputError
    from phirie_jax.io.scene import load_scene
    from phirie_jax.render import render as render_camera
    from phirie_jax.synthetic.scene import write_png

    with outside_paths_allowed(allow_outside_paths):
        loaded = load_scene(scene, gaussians=gaussians, check_images=False)
    cameras = loaded.require_cameras()
    if not 0 <= camera < len(cameras):
        raise SceneInputError(loaded.camera_source, "--camera",
                              f"{camera} (expected 0..{len(cameras) - 1})")
    cam = cameras[camera]
    if width is not None:
        cam = cam.scaled(width / cam.width)
    result = render_camera(loaded.require_gaussians().to_kernel(), cam,
                           background=np.asarray(background, np.float32))
    write_png(out, np.asarray(result.rgb))
    print(f"wrote {out} ({cam.width}×{cam.height}, camera {camera}: {cam.name})")


def _print_instances(manifest: Manifest) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title="instances")
    for column in ("id", "category", "views", "points", "confidence", "source"):
        table.add_column(column)
    for inst in manifest.get("instances", ()):
        confidence = float("nan") if inst.confidence is None else inst.confidence
        table.add_row(str(inst.id), str(inst.category or "—"), str(len(inst.views)),
                      f"{inst.num_points:,}", f"{confidence:.2f}", str(inst.source))
    console = Console()
    console.print(table)
    rejected = manifest.get("observe", {}).get("rejected_proposals", [])
    console.print(f"{len(rejected)} proposals rejected (reasons in manifest.json)")


def _print_timings(manifest: Manifest) -> None:
    """Each stage's seconds, its steps indented under it (``stage.step`` keys)."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title="timings (s)")
    table.add_column("stage")
    table.add_column("seconds", justify="right")
    timings = manifest.timings.values
    stages = dict.fromkeys(key.partition(".")[0] for key in timings)  # in the order they ran
    for stage in stages:
        table.add_row(stage, f"{timings[stage]:.1f}" if stage in timings else "")
        for key, seconds in timings.items():
            if key.startswith(stage + "."):
                table.add_row(f"  {key[len(stage) + 1:]}", f"{seconds:.1f}")
    Console().print(table)


def observe(scene: Scene, out: Path, masks: str | None = None, gaussians: Path | None = None,
            surface: Path | None = None, frame: Annotated[FrameConfig, tyro.conf.OmitArgPrefixes] = FrameConfig(),
            observe_width: int | None = None, prompt: Prompts = (), config: ObserveConfig = ObserveConfig(),
            allow_outside_paths: bool = False) -> None:
    """Scene Observation alone (after the frame: up and metres): masks → first-hit lifting onto
    the surface → voxel association into object instances (manifest.json `instances`,
    observe/instance_<id>.npz).

    Args:
        scene: a scene folder.
        out: output folder (manifest.json is created or updated).
        masks: "files" (masks/ or ScanNet++ annotations), "auto" (support planes + clusters,
            no learned weights), or a folder of an external segmenter's <image stem>.png
            (+ <image stem>.json); default: files when the scene has them, else auto.
        gaussians: Gaussian PLY to use instead of the one found in the folder.
        surface: scene surface mesh to use instead of the one found (none: built from the splats).
        frame: the capture's up and scale, when known (else estimated and recorded).
        observe_width: observation's working width in pixels, whatever the photos' size
            (same as --config.working-width; 0 = the photos' size).
        prompt: one object, pointed at in one photo: IMAGE:X0,Y0,X1,Y1 (a box) or IMAGE:U,V (a
            click) in the pixel coordinates an image viewer shows, optionally =LABEL (its
            category); IMAGE is the photo's name (0007.jpg) or stem. Repeat for more objects;
            default: the scene's prompts.json, if any.
        config: observation parameters (defaults: the paper's numbers).
        allow_outside_paths: accept cameras that name images outside the scene folder (refused by default).
    """
    config = _with_observe_width(config, observe_width)
    manifest = _run_stages(scene, out, ConvertConfig(observe=config), masks, gaussians, surface, frame,
                           ("observe",), allow_outside_paths, prompt)
    _print_frame(manifest)
    _print_instances(manifest)
    _print_outcome(manifest)
    _print_timings(manifest)


def convert(scene: Scene, out: Path, masks: str | None = None, gaussians: Path | None = None,
            surface: Path | None = None, frame: Annotated[FrameConfig, tyro.conf.OmitArgPrefixes] = FrameConfig(),
            observe_width: int | None = None, prompt: Prompts = (), mass: tuple[str, ...] = (),
            config: ConvertConfig = ConvertConfig(), allow_outside_paths: bool = False) -> None:
    """Scene → interactive scene: frame (metres, +z up) → observe → objects → background →
    physics, each adding to OUT/manifest.json (frame; instances; objects with meshes, visual
    Gaussians, checks; background.ply with the objects removed and what they uncover filled;
    collision, built while the background runs, scene.xml, URDFs, drop tests). Every output is in
    the metric, +z-up world frame.

    Args:
        scene: a scene folder.
        out: output folder.
        masks: mask source for observation: "files", "auto" or an external segmenter's folder.
        gaussians: Gaussian PLY to use instead of the one found in the folder.
        surface: scene surface mesh to use instead of the one found.
        frame: the capture's up and scale, when known (else estimated and recorded).
        observe_width: observation's working width in pixels, whatever the photos' size
            (same as --config.observe.working-width; 0 = the photos' size).
        prompt: one object, pointed at in one photo: IMAGE:X0,Y0,X1,Y1 (a box) or IMAGE:U,V (a
            click) in the pixel coordinates an image viewer shows, optionally =LABEL (its
            category); IMAGE is the photo's name (0007.jpg) or stem. Prompt k is object k. Repeat
            for more objects; default: the scene's prompts.json, if any (`phirie view SCENE` writes it).
        mass: ID=KG, an object's mass (repeatable: --mass 3=0.35 --mass 5=0.12); others get their
            category's (a mask's or a prompt's label) or the paper's 0.3 kg.
        config: every stage's parameters (defaults: the paper's numbers).
        allow_outside_paths: accept cameras (transforms.json frames, COLMAP image names) that name
            images outside the scene folder; refused by default, before anything reads them.
    """
    config = dataclasses.replace(config, observe=_with_observe_width(config.observe, observe_width))
    if mass:
        config = dataclasses.replace(config, physics=dataclasses.replace(
            config.physics, object_masses=config.physics.object_masses + _object_masses(mass)))
    manifest = _run_stages(scene, out, config, masks, gaussians, surface, frame, None, allow_outside_paths, prompt)
    _print_frame(manifest)
    _print_instances(manifest)
    _print_objects(manifest)
    _print_background(manifest)
    _print_outcome(manifest)
    _print_timings(manifest)
    if (manifest.get("report") or {}).get("path"):
        print(f"report: {out / manifest.get('report')['path']}")


def convert_many(scenes: Annotated[tuple[Path, ...], tyro.conf.Positional], out: Path, address: str | None = None,
                 workers: int | None = None, cpus_per_scene: int = 1, gpus_per_scene: float | None = None,
                 resources: tuple[str, ...] = (), retries: int = 2, masks: str | None = None,
                 frame: Annotated[FrameConfig, tyro.conf.OmitArgPrefixes] = FrameConfig(),
                 observe_width: int | None = None, config: ConvertConfig = ConvertConfig(),
                 allow_outside_paths: bool = False) -> None:
    """Convert many scenes, each a Ray task writing OUT/<scene name>/ (as `phirie convert`); a
    summary table and OUT/summary.json at the end. A scene that fails is recorded with its reason
    and the others go on; a task whose worker dies is retried; a re-run skips the scenes already
    converted from the same inputs with the same options. Needs Ray: pip install 'phirie_jax[cluster]'.

    Args:
        scenes: scene folders (their names name the output folders; alike names are told apart by
            their parent folders).
        out: the folder that holds one output folder per scene, and summary.json.
        address: a running Ray cluster: auto (the one on this machine or RAY_ADDRESS), HOST:PORT or
            ray://HOST:PORT; default: a local Ray instance started for this run.
        workers: CPUs of the local instance, i.e. scenes at once (default: every core).
        cpus_per_scene: CPUs each scene's task holds (its collision's worker processes).
        gpus_per_scene: GPUs each scene's task holds (default: 1 when the cluster has a GPU, else 0;
            a fraction shares a GPU).
        resources: NAME=AMOUNT, a custom Ray resource each task holds (repeatable).
        retries: attempts after the first, for a task whose worker died or that failed transiently.
        masks: mask source for observation: "files", "auto" or an external segmenter's folder.
        frame: the captures' up and scale, when the same for all (else each scene's frame.json or
            estimate).
        observe_width: observation's working width in pixels (as --config.observe.working-width).
        config: every stage's parameters (defaults: the paper's numbers).
        allow_outside_paths: accept cameras that name images outside the scene folder.
    """
    from phirie_jax.cluster.driver import SUMMARY, Placement, import_ray
    from phirie_jax.cluster.driver import convert_many as run_many
    from phirie_jax.cluster.scene_task import SceneJob
    from phirie_jax.cluster.table import ended_line, print_summary

    import_ray()
    check_option("--workers", workers, AT_LEAST_ONE)
    check_option("--cpus-per-scene", cpus_per_scene, AT_LEAST_ONE)
    check_option("--retries", retries, NON_NEGATIVE)
    if gpus_per_scene is not None and not gpus_per_scene >= 0:
        raise OptionError("--gpus-per-scene", "expected >= 0", str(gpus_per_scene))
    if workers is not None and address not in (None, "local"):
        raise OptionError("--workers", "sets the CPUs of a local Ray instance (expected no --address; a running "
                          "cluster has its own)")
    config = dataclasses.replace(config, observe=_with_observe_width(config.observe, observe_width))
    placement = Placement(address=None if address == "local" else address, workers=workers, cpus=cpus_per_scene,
                          gpus=gpus_per_scene, resources=_resource_amounts(resources), retries=retries)
    job = SceneJob(name="", scene=Path(), out=Path(), config=config, masks=masks, frame=frame,
                   allow_outside_paths=allow_outside_paths)

    def started(meta: dict) -> None:
        cluster = meta["cluster"]
        where = "a local Ray instance" if meta["address"] == "local" else f"the Ray cluster at {meta['address']}"
        print(f"phirie: {len(scenes)} scenes on {where} ({cluster.get('CPU', 0):g} CPUs, {cluster.get('GPU', 0):g} "
              f"GPUs; each scene {meta['task']['num_cpus']:g} CPU, {meta['task']['num_gpus']:g} GPU)", flush=True)

    summary = run_many(scenes, out, job, placement, on_start=started,
                       on_end=lambda record: print(ended_line(record), flush=True))
    print_summary(summary)
    print(f"summary: {out / SUMMARY}")
    failed = summary["counts"].get("failed", 0)
    if failed:
        raise ScenesFailed(f"{failed} of {len(scenes)} scenes failed (reasons in {out / SUMMARY})")


def _resource_amounts(given: tuple[str, ...]) -> dict[str, float]:
    """``--resources NAME=AMOUNT`` values as {name: amount}; ``OptionError`` for a malformed one."""
    import math

    amounts = {}
    for text in given:
        name, sep, amount = text.partition("=")
        try:
            value = float(amount)
        except ValueError:
            value = math.nan
        if not sep or not name or not (math.isfinite(value) and value > 0):
            raise OptionError("--resources", f"{text!r} (expected NAME=AMOUNT with a positive amount, e.g. bigmem=1)")
        amounts[name] = value
    return amounts


def _object_masses(given: tuple[str, ...]) -> tuple[tuple[int, float], ...]:
    """``--mass ID=KG`` values as (id, kg) pairs; ``OptionError`` for a malformed one."""
    import math

    pairs = []
    for text in given:
        ident, sep, kg = text.partition("=")
        try:
            pair = (int(ident), float(kg))
        except ValueError:
            pair = None
        if not sep or pair is None or pair[0] < 0 or not (math.isfinite(pair[1]) and pair[1] > 0):
            raise OptionError("--mass", f"{text!r} (expected ID=KG with a positive mass, e.g. 3=0.35)")
        pairs.append(pair)
    return tuple(pairs)


def _with_observe_width(config: ObserveConfig, observe_width: int | None) -> ObserveConfig:
    """``--observe-width`` (checked here: the config's own check would name --config...working-width)."""
    if observe_width is None:
        return config
    check_option("--observe-width", observe_width, NON_NEGATIVE)
    return dataclasses.replace(config, working_width=observe_width)


def _run_stages(scene: Path, out: Path, config: ConvertConfig, masks, gaussians, surface, frame: FrameConfig,
                stages: tuple[str, ...] | None, allow_outside_paths: bool, prompts: tuple[str, ...] = ()) -> Manifest:
    """``run_convert`` showing its progress (``progress.display_for``): bars on a terminal, else a
    line as each stage and long step starts and ends, with elapsed times. After a whole conversion,
    ``report.html`` (``config.report``; a failure to write it is one line, not the run's failure)."""
    import time

    from phirie_jax.pipeline import run_convert
    from phirie_jax.progress import display_for, showing, task

    options = dict(masks=masks, gaussians=gaussians, surface=surface, frame=frame, stages=stages,
                   allow_outside_paths=allow_outside_paths, prompts=prompts)
    start = time.perf_counter()
    with showing(display_for()):
        run_convert(scene, out, config, **options)
        if stages is None and config.report.enabled and not Manifest.load(out).get("failed_stage"):
            with task("report"):
                _write_report(out, config.report)
    print(f"phirie: done in {time.perf_counter() - start:.0f} s", flush=True)
    return Manifest.load(out)


def _write_report(out: Path, config, video: Path | None = None, frames=()) -> bool:
    """Write ``OUT/report.html``; False (and says why) when it failed."""
    from phirie_jax import layout
    from phirie_jax.report.page import write_report

    try:
        write_report(out, config, video=video, frames=frames)
    except Exception as err:  # noqa: BLE001 — the conversion stands; its report is a view of it
        print(f"phirie: {out / layout.REPORT} not written: {type(err).__name__}: {err}", file=sys.stderr, flush=True)
        return False
    return True


def _print_frame(manifest: Manifest) -> None:
    frame = manifest.frame()
    if frame is not None:
        support = frame.support
        print(f"frame: {frame.scale:.6g} m per capture unit ({frame.scale_source}, within ×/÷"
              f"{frame.scale_uncertainty:g}); up {[round(float(v), 4) for v in frame.capture_up]} "
              f"({frame.up_source}); "
              + (f"support: {support['source']} at {support['height']:.3g} m" if support else "no support plane"))


def _print_outcome(manifest: Manifest) -> None:
    """What the run made, and why when it made nothing."""
    from phirie_jax.info import outcome_lines

    for text in outcome_lines(manifest):
        print(text)


def _print_background(manifest: Manifest) -> None:
    from rich.console import Console
    from rich.table import Table

    b = manifest.background()
    if b is None:
        return
    table = Table(title=f"background: {b.source_gaussians} → {b.gaussians} Gaussians "
                        f"({b.removed} removed, {b.filled} filled)")
    for column in ("id", "status", "removed", "disks", "view", "reason"):
        table.add_column(column)
    for obj in b.objects:
        removed = obj.get("removed") or {}
        table.add_row(str(obj["id"]), obj["status"], str(removed.get("union", "—")),
                      str((obj.get("fill") or {}).get("disks", "—")), str((obj.get("primary_view") or {}).get("view", "—")),
                      str(obj.get("reason") or ""))
    Console().print(table)


def _print_objects(manifest: Manifest) -> None:
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    from phirie_jax.info import STATUS_COLOURS, candidate_name, status_words

    table = Table(title="objects")
    for column in ("id", "status", "candidate", "failed checks", "drop test", "reason"):
        table.add_column(column)
    for obj in manifest.get("objects", ()):
        failed = obj.failed_checks
        drop = obj.drop_test or {}
        drift = drop.get("drift_m")
        verdict = "—" if not drop else ("stable" if drop.get("stable") else "unstable") + (
            f" ({100 * drift:.1f} cm)" if drift is not None else f" ({drop.get('error') or 'not measured'})")
        colour = STATUS_COLOURS.get(obj.status, "default")
        table.add_row(str(obj.id), f"[{colour}]{escape(status_words(obj))}[/]", candidate_name(obj),
                      ", ".join(failed) or "—", verdict, "" if obj.accepted else str(obj.reason or ""))
    Console().print(table)


def droptest(out: Annotated[Path, tyro.conf.Positional], config: PhysicsConfig = PhysicsConfig()) -> None:
    """Re-run the drop tests (the paper's protocol) on an exported folder and update its manifest.

    Args:
        out: a `phirie convert` output folder.
        config: physics and drop-test parameters.
    """
    from phirie_jax.construct.physics.stage import run_droptest
    from phirie_jax.io.output_folder import locked

    if not out.is_dir():
        raise SceneInputError(out, None, "not a folder (expected a phirie convert output folder)")
    with locked(out):
        run_droptest(out, config)
        _print_objects(Manifest.load(out))


def simulate(out_dir: Annotated[Path, tyro.conf.Positional], out: Path = Path("rollout.mp4"),
             shoot: tuple[float, float] | None = None, frames: int = 48, camera: int | None = None,
             speed: float = 2.5, width: int | None = None, fps: float | None = None,
             robot: str | None = None, robot_base: tuple[float, float, float, float] | None = None,
             task: Literal["shoot", "pick-place"] = "shoot", object: int | None = None,
             to: tuple[float, float] | None = None) -> None:
    """Simulate a converted scene and render the rollout to a video from one of its cameras.
    Default: shoot the largest object off its support so the filled background shows. With
    `--robot panda --task pick-place` the arm picks `--object` and places it at `--to X Y`,
    filmed from a scene camera and its wrist camera side by side.

    Args:
        out_dir: a `phirie convert` output folder.
        out: the video to write (.mp4).
        shoot: pixel (u, v) of the camera to shoot through; default: the largest object's centre.
        frames: frames rendered after the shot.
        camera: camera index K (the K-th image in name order); default: 0 for a shot, for a
            pick-and-place the camera that sees the object, the goal and the robot.
        speed: speed (m/s) the shot gives the hit object, along the ray.
        width: render width in pixels (default: the camera's).
        fps: frames per second of simulated time and of the video (default 24; 12 for pick-place).
        robot: a robot merged into the scene: `panda` (pip install 'phirie_jax[robot]') or the
            path of an MJCF file.
        robot_base: X Y Z YAW_DEG of the robot's base (default: beside the largest support).
        task: `shoot` or `pick-place` (needs a robot; `panda` when none is named).
        object: the object id to pick (default: the first the gripper fits and the arm reaches).
        to: X Y goal of the picked object on its support (default: a free spot 15 cm away).
    """
    from rich.console import Console

    from phirie_jax import layout
    from phirie_jax.interact.environment import Environment
    from phirie_jax.interact.rollout import RolloutConfig, rollout, write_video

    if task == "pick-place":
        from phirie_jax.interact.rollout import simulate_pick_place

        result = simulate_pick_place(out_dir, out, robot or "panda", robot_base, object, to, camera, width, fps)
        o = result["outcome"]
        print(f"wrote {out} ({len(result['frames'])} frames, camera {result['camera']} | wrist); object {o['object']} "
              f"{'placed' if o['success'] else 'missed'}: {100 * o['distance_m']:.1f} cm from ({o['goal'][0]:.3f}, "
              f"{o['goal'][1]:.3f}), tilted {o['tilt_deg']:.1f}°")
        return
    fps = 24.0 if fps is None else fps
    try:
        config = RolloutConfig(frames=frames, fps=fps, camera=camera or 0, width=width, speed=speed, shoot_at=shoot)
    except ConfigValueError as err:  # the options are the config's fields, --shoot for shoot_at
        option = "--shoot" if err.field == "shoot_at" else "--" + err.field.replace("_", "-")
        raise OptionError(option, f"expected {err.expected}", err.shown) from None
    env = Environment.load(out_dir, robot=_robot_config(robot, robot_base))
    with Console().status("simulating") as status:
        result = rollout(env, config, on_frame=lambda i: status.update(f"frame {i + 1}/{frames}"))
    write_video(out, result["frames"], fps)
    if (Path(out_dir) / layout.REPORT).is_file():  # the report shows the rollout too
        _write_report(Path(out_dir), ReportConfig(), video=out, frames=result["frames"])
    hit = result["shot"].get("hit")
    moved = ", ".join(f"{k}: {100 * v:.1f} cm" for k, v in result["moved_m"].items())
    print(f"wrote {out} ({len(result['frames'])} frames); shot hit object {hit}; moved {moved}")


def _robot_config(robot: str | None, base):
    if robot is None:
        if base is not None:
            raise OptionError("--robot-base", "needs --robot")
        return None
    from phirie_jax.interact.robot.config import RobotConfig

    try:
        return RobotConfig(model=robot, base=base)
    except ConfigValueError as err:
        raise OptionError("--robot-base", f"expected {err.expected}", err.shown) from None


def demo(out: Path = Path("out/demo"), preset: Literal["tiny", "default", "large"] = "default",
         seed: int = 0) -> None:
    """The whole job on the embedded default scene (what `make demo` runs).

    Args:
        out: output folder.
        preset: synthetic scene preset.
        seed: synthetic scene seed.
    """
    check_option("--seed", seed, NON_NEGATIVE)
    from phirie_jax.demo import run_demo

    run_demo(out, preset=preset, seed=seed)


def view(out_dir: Annotated[Path, tyro.conf.Positional],
         settings: Annotated[ViewConfig, tyro.conf.OmitArgPrefixes] = ViewConfig()) -> None:
    """Serve a converted scene to the browser (viser; needs the viewer extra): its Gaussians, the
    capture's cameras and a live MuJoCo simulation. Click an object to shoot it, drag it to push
    it; play / pause / reset, collision parts, completed meshes, instance colours, the source
    capture and each object's record are in the panel. Runs until Ctrl-C; no GPU needed.
    On a scene folder (not converted yet): its Gaussians and cameras; clicking an object adds a
    prompt to SCENE/prompts.json (the one file it writes there), which `phirie convert` reads.

    Args:
        out_dir: a `phirie convert` output folder, or a scene folder to pick objects in.
        settings: the viewer's settings (--port, --host, --no-playing, ...).
    """
    import time

    from phirie_jax.view.server import Viewer

    try:  # the options are the config's fields (no prefix): checked here, named as typed
        settings = dataclasses.replace(settings)
    except ConfigValueError as err:
        raise OptionError("--" + err.field.replace("_", "-"), f"expected {err.expected}", err.shown) from None
    from phirie_jax.info import is_converted

    if is_converted(out_dir):
        viewer = Viewer(out_dir, settings)
    else:
        from phirie_jax.view.capture import CaptureViewer

        viewer = CaptureViewer(out_dir, settings)
    print(f"phirie view: {viewer.url} (Ctrl-C to stop)", flush=True)
    try:
        while True:
            time.sleep(3600)
    finally:
        viewer.close()


COMMANDS = {"info": info, "synth": synth, "render": render, "observe": observe,
            "convert": convert, "convert-many": convert_many, "droptest": droptest, "simulate": simulate, "demo": demo, "view": view,
            "capture": capture}


def _options_checked(command):
    """``command`` with its ``--config`` options checked before it starts.

    ``main`` has tyro build the configs with their range checks deferred (tyro would box a
    config's ValueError and name the config, not the option); here, first thing, the checks
    resume and run on the whole config, so a bad value is one line naming its option.
    """
    signature = inspect.signature(command)

    @functools.wraps(command)
    def checked(*args, **kwargs):
        config = signature.bind_partial(*args, **kwargs).arguments.get("config")
        if config is None:
            resume_checks()
        else:
            check_options(config, "--config")
        return command(*args, **kwargs)

    return checked


def version() -> str:
    """The installed distribution's version."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as installed

    try:
        return installed("phirie_jax")
    except PackageNotFoundError:
        return "unknown (not installed: pip install -e .)"


def main(argv: list[str] | None = None) -> int:
    if (sys.argv[1:] if argv is None else argv)[:1] in (["--version"], ["-V"]):
        print(f"phirie {version()}")
        return 0
    use_compile_cache()
    try:
        with deferred_checks():
            tyro.extras.subcommand_cli_from_dict(
                {name: _options_checked(command) for name, command in COMMANDS.items()}, prog="phirie", args=argv,
                description="Turn a 3D Gaussian Splatting capture into an interactive simulation scene "
                            "(phirie --version: the version).",
            )
    except (SceneInputError, OptionError, ConfigValueError) as err:
        print(f"phirie: error: {err}", file=sys.stderr)
        return 2
    except StageError as err:
        print(f"phirie: error: {err} (recorded in the output folder's manifest.json)", file=sys.stderr)
        return 1
    except ScenesFailed as err:
        print(f"phirie: error: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("phirie: interrupted", file=sys.stderr)
        return 130
    except OSError as err:  # a path that cannot be read or written: the system's one line says which
        print(f"phirie: error: {err}", file=sys.stderr)
        return 1
    return 0


def entry_point() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entry_point()
