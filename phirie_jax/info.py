"""What a scene folder, or a converted one, holds, as a dict of facts (``phirie info``); the
readers of a converted folder's object records that the command line, the viewer and the report
share (``candidate_name``, ``chosen_scores``, ``drop_verdict``, ``outcome_lines``)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np

from phirie_jax import layout
from phirie_jax.errors import SceneInputError
from phirie_jax.io.gaussian_checks import degenerate_counts
from phirie_jax.io.ply import ply_element_counts, read_gaussian_ply
from phirie_jax.manifest import UNVERIFIED, Manifest
from phirie_jax.records import ObjectRecord
from phirie_jax.types import GaussianSplatData, SceneInput


def _relative(path: Path | None, root: Path) -> str | None:
    if path is None:
        return None
    try:
        return str(path.relative_to(root))
    except ValueError:
        return str(path)


def _mesh_facts(path: Path) -> dict:
    facts = {"path": str(path), "bytes": path.stat().st_size}
    if path.suffix.lower() == ".ply":
        try:
            counts = ply_element_counts(path)
            facts.update(vertices=counts.get("vertex"), faces=counts.get("face"))
        except SceneInputError as err:
            facts["problem"] = str(err)
    return facts


def degenerate_facts(path: Path) -> dict:
    """``{"total": N, reason: count, ...}`` for the degenerate Gaussians of a Gaussian PLY.

    Read from the file itself: a loaded scene has already dropped them.
    """
    counts = degenerate_counts(read_gaussian_ply(path, allow_non_finite=True))
    return {"total": sum(counts.values()), **counts}


def _gaussian_facts(g: GaussianSplatData, path: Path | None, root: Path) -> dict:
    return {
        "path": _relative(path, root),
        "count": g.num,  # kept: the degenerate ones are dropped, as every stage does
        "degenerate": degenerate_facts(path) if path is not None else None,
        "sh_degree": g.sh_degree,
        "extra_properties": list(g.extra),
        "mean_opacity": round(float(np.mean(1.0 / (1.0 + np.exp(-g.opacity_logits)))), 4)
        if g.num else None,
    }


def scene_facts(scene: SceneInput) -> dict:
    """A JSON-ready summary: layout, Gaussians (with the degenerate ones counted by reason), cameras,
    images, surface, masks, candidates, bounds."""
    facts: dict = {"root": str(scene.root), "layout": scene.layout}
    g = scene.gaussians
    facts["gaussians"] = None if g is None else _gaussian_facts(g, scene.gaussians_path, scene.root)
    cams = scene.cameras
    if cams:
        sizes = Counter(f"{c.width}x{c.height}" for c in cams)
        focal = np.array([[c.K[0, 0], c.K[1, 1]] for c in cams])
        facts["cameras"] = {
            "source": _relative(scene.camera_source, scene.root),
            "count": len(cams),
            "models": dict(Counter(c.model for c in cams)),
            "distorted": sum(c.is_distorted for c in cams),
            "image_sizes": dict(sizes),
            "focal_px": [float(focal.min()), float(focal.max())],
            "first": cams[0].name,
            "last": cams[-1].name,
        }
        folders = Counter(str(c.image_path.parent) for c in cams if c.image_path)
        facts["images"] = {"folders": [_relative(Path(f), scene.root) for f in folders], "count": len(cams)}
    else:
        facts["cameras"] = None
    if scene.sparse_points is not None:
        facts["sparse_points"] = len(scene.sparse_points)
    facts["surface_mesh"] = _mesh_facts(scene.surface_mesh) if scene.surface_mesh else None
    if scene.surface_mesh is not None:
        facts["surface_mesh"]["path"] = _relative(scene.surface_mesh, scene.root)
    facts["masks"] = (
        None if scene.masks is None
        else {"found": sum(m is not None for m in scene.masks), "cameras": len(scene.masks)}
    )
    facts["candidates"] = {
        str(i): [{"name": c.name, "mesh": _relative(c.mesh, scene.root),
                  "gaussians": _relative(c.gaussians, scene.root)} for c in entries]
        for i, entries in scene.candidates.items()
    } or None
    bounds = scene.bounds()
    facts["bounds"] = None if bounds is None else [[round(float(v), 4) for v in row] for row in bounds]
    return facts


# How each object status is shown (terminal, report, viewer): unverified in yellow.
STATUS_COLOURS = {"accepted": "green", "unverified": "yellow", "rejected": "red", "failed": "red"}


def status_words(entry: ObjectRecord) -> str:
    """An object's status with what it failed: ``unverified (failed registration)``; a mounted
    object (welded to its wall) says so: ``accepted, mounted``."""
    return status_text(entry.status, entry.unresolved_checks, entry.mounted)


def status_text(status: str, failed_checks: list[str] | None, mounted: bool = False) -> str:
    """``status_words`` of a status, the checks an unverified object failed, and whether it is mounted."""
    words = str(status) + (", mounted" if mounted else "")
    if status == UNVERIFIED and failed_checks:
        return f"{words} (failed {', '.join(failed_checks)})"
    return words


def candidate_name(entry: ObjectRecord) -> str:
    """The chosen candidate's name (the manifest holds a name, or a record with one)."""
    candidate = entry.candidate
    return str(candidate.get("name") if isinstance(candidate, dict) else candidate or "—")


def chosen_scores(entry: ObjectRecord) -> dict:
    """The scores of the chosen candidate among those tried (empty when not recorded)."""
    name = candidate_name(entry)
    return next((c.get("scores") or {} for c in entry.candidates if c.get("name") == name), {})


def drop_verdict(entry: ObjectRecord) -> str:
    """The drop test in words: stable / unstable with the drift, or why it was not run."""
    drop = entry.drop_test or {}
    if not drop:
        return "not run"
    if drop.get("error"):
        return f"not measured ({drop['error']})"
    drift = drop.get("drift_m")
    verdict = "stable" if drop.get("stable") else "unstable"
    if entry.mounted:
        verdict = ("held" if drop.get("stable") else "not held") + " by its weld"
    return verdict + (f", drift {100 * drift:.1f} cm" if drift is not None else "")


def _reasons(entries: list[dict]) -> str:
    counts = Counter(str(e.get("reason") or "no reason recorded") for e in entries)
    return "; ".join(f"{reason} (×{n})" if n > 1 else reason for reason, n in counts.most_common(4))


def _unverified(entry: ObjectRecord) -> str:
    """``5: failed registration, settling`` for an unverified object."""
    return f"{entry.id}: failed {', '.join(entry.unresolved_checks or []) or 'a check'}"


def outcome_lines(manifest: Manifest) -> list[str]:
    """What a conversion made, and why when it made nothing (the CLI prints these lines)."""
    lines = []
    failed = manifest.get("failed_stage")
    if failed:
        lines.append(f"stage {failed['stage']} failed: {failed['error']}")
    observe = manifest.get("observe") or {}
    if manifest.get("instances") == ():
        clusters = (observe.get("auto") or {}).get("rejected_clusters") or []
        views = (observe.get("masks") or {}).get("failed_views") or []
        why = [text for text in (_reasons(clusters) if clusters else "",
                                 f"proposals rejected: {_reasons(observe['rejected_proposals'])}"
                                 if observe.get("rejected_proposals") else "",
                                 f"{len(views)} views gave no masks: {_reasons(views)}" if views else "") if text]
        lines.append("no object instance found: " + ("; ".join(why) or "no mask labels any pixel"))
    physics = manifest.physics()
    usd = (physics.usd if physics is not None else None) or {}
    if usd.get("reason"):
        lines.append(f"scene.usda not written: {usd['reason']}")
    objects = manifest.get("objects")
    if objects:
        accepted, kept = manifest.accepted_objects(), manifest.kept_objects()
        unverified = [o for o in kept if not o.accepted]
        if kept:
            lines.append(f"{len(accepted)} of {len(objects)} objects accepted" + (
                f", {len(unverified)} kept unverified ({'; '.join(_unverified(o) for o in unverified)})"
                if unverified else ""))
        else:
            lines.append("no object kept: " + "; ".join(f"{o.id}: {o.reason or o.status}" for o in objects))
    return lines


def is_converted(path: Path) -> bool:
    """Whether ``path`` is a ``phirie convert`` output folder (it holds ``manifest.json``)."""
    return Path(path).is_dir() and (Path(path) / layout.MANIFEST).is_file()


# What a converted folder holds, in the order shown (``layout`` names them once).
CONVERTED_FILES = (layout.SCENE_MJCF, layout.SCENE_USD, layout.BACKGROUND, layout.CAMERAS, layout.REPORT)


def conversion_state(out_dir: Path, manifest) -> str:
    """"converted" when every stage completed; else which stage did not and why, e.g. "incomplete:
    the physics stage did not finish (...)", or "partial: ..." for a folder of ``phirie observe``;
    says so when a conversion holds the folder now."""
    from phirie_jax.io.output_folder import running_holder
    from phirie_jax.manifest import COMPLETE, describe_status

    status = manifest.stage_status()
    unfinished = {name: s for name, s in status.items() if s != COMPLETE}
    holder = running_holder(out_dir)
    now = f"; a conversion is running now: {holder}" if holder else ""
    if not unfinished:
        return "converted" + now
    done = [name for name, s in status.items() if s == COMPLETE]
    if done and set(unfinished.values()) == {"not run"} and list(status)[:len(done)] == done:
        return f"partial: {', '.join(done)} ran; {', '.join(unfinished)} not run" + now
    name, first = next(iter(unfinished.items()))
    return f"incomplete: the {name} stage {describe_status(first)}" + now


def converted_facts(out_dir: Path) -> dict:
    """A JSON-ready summary of a converted folder: its state (``conversion_state``), scene, frame,
    outcome, each object's record, the background, the files written (bytes; "not written" when
    absent) and the stages' seconds."""
    out_dir = Path(out_dir)
    manifest = Manifest.load_or_create(out_dir)
    state = conversion_state(out_dir, manifest)
    frame = manifest.frame()
    background = manifest.background()
    objects = [{"id": o.id, "status": str(o.status), "failed_checks": o.unresolved_checks or [],
                "mounted": o.mounted, "candidate": candidate_name(o), "drop_test": drop_verdict(o), "mass": o.mass,
                "mass_source": ((o.physics or {}).get("priors") or {}).get("mass_source"),
                "friction": o.friction, "parts": len(o.collision) or None,
                "reason": None if o.accepted else o.reason}
               for o in manifest.get("objects", ())]
    files = {name: (out_dir / name).stat().st_size if (out_dir / name).is_file() else None
             for name in CONVERTED_FILES}
    physics = manifest.physics()
    usd = (physics.usd if physics is not None else None) or {}
    return {
        "root": str(out_dir),
        "state": state,
        "stages": manifest.stage_status(),
        "scene": (manifest.get("scene") or {}).get("path"),
        "frame": None if frame is None else (f"{1.0 if frame.scale is None else frame.scale:.6g} m per capture unit "
                                             f"({frame.scale_source}); up from {frame.up_source}"),
        "outcome": ([] if state.startswith("converted") else [state]) + outcome_lines(manifest),
        "objects": objects,
        "background": None if background is None else (
            f"{background.source_gaussians} → {background.gaussians} Gaussians "
            f"({background.removed} removed, {background.filled} filled)"),
        "files": {name: size if size is not None else ("not written: " + usd["reason"]
                                                        if name == layout.SCENE_USD and usd.get("reason") else
                                                        "not written")
                  for name, size in files.items()},
        "timings_s": {k: round(float(v), 1) for k, v in manifest.timings.values.items() if "." not in k},
    }
