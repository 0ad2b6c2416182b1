"""``report.html`` (``layout.REPORT``): one self-contained page of what a conversion made.

Images are inlined as base64 PNG, styles are inline: the file can be mailed or attached to an
issue alone. Sections: a summary (objects accepted, frame, outputs), before / after renders from a
few cameras, one row per object (thumbnail, candidate, scores, checks, drop test, mass and
friction, reason), the background's removal and fill, the stages' timings, and the rollout when
one was made (a strip of its frames inline, the video linked). Written atomically.
"""

from __future__ import annotations

import base64
import html
import os
from pathlib import Path

import cv2
import numpy as np

from phirie_jax import layout
from phirie_jax.info import candidate_name, chosen_scores, drop_verdict, outcome_lines, status_words
from phirie_jax.io.atomic import write_text
from phirie_jax.manifest import Manifest
from phirie_jax.records import Check
from phirie_jax.report.config import ReportConfig
from phirie_jax.report.renders import ReportImages, render_images
from phirie_jax.types import GaussianSplatData

STYLE = """
body { font: 14px/1.45 system-ui, sans-serif; margin: 24px auto; max-width: 1200px; color: #222; }
h1 { font-size: 22px; } h2 { font-size: 17px; margin-top: 28px; border-bottom: 1px solid #ddd; }
table { border-collapse: collapse; } td, th { padding: 4px 8px; border-bottom: 1px solid #eee;
text-align: left; vertical-align: top; } th { background: #f6f6f6; }
img { display: block; image-rendering: auto; } .pass { color: #1a7f37; } .fail { color: #c62828; }
.muted { color: #777; } .num { text-align: right; font-variant-numeric: tabular-nums; }
.strip img { display: inline-block; margin-right: 4px; }
.status-accepted { color: #1a7f37; } .status-unverified { color: #9a6700; background: #fff8c5; }
.status-rejected, .status-failed { color: #c62828; }
"""


def _e(value) -> str:
    return html.escape("—" if value is None else str(value))


def _number(value, digits: int = 3) -> str:
    if value is None or isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        return _e(value)
    return f"{value:.{digits}g}"


def png_data_uri(image: np.ndarray) -> str:
    """An (H, W, 3) uint8 RGB image as a ``data:image/png;base64,...`` URI."""
    ok, encoded = cv2.imencode(".png", np.ascontiguousarray(image[..., ::-1]))
    if not ok:
        raise RuntimeError("OpenCV could not encode a PNG")
    return "data:image/png;base64," + base64.b64encode(encoded.tobytes()).decode("ascii")


def _img(image: np.ndarray | None, alt: str, scale: float = 1.0) -> str:
    if image is None:
        return f'<span class="muted">{_e(alt)}: not available</span>'
    height, width = image.shape[:2]
    return (f'<img src="{png_data_uri(image)}" alt="{_e(alt)}" width="{int(width * scale)}" '
            f'height="{int(height * scale)}">')


def _summary(manifest: Manifest) -> str:
    scene = manifest.get("scene") or {}
    frame = manifest.frame()
    physics = manifest.physics()
    usd = (physics.usd if physics is not None else None) or {}
    rows = [("scene", scene.get("path")), ("Gaussians", scene.get("gaussians")),
            ("cameras", scene.get("cameras")),
            ("frame", f"{_number(frame.scale, 6)} m per capture unit ({frame.scale_source}), "
                      f"up from {frame.up_source}" if frame is not None else None),
            ("outcome", "; ".join(outcome_lines(manifest)) or None),
            ("simulation", f"{physics.scene or layout.SCENE_MJCF}; "
                           + (f"{usd['path']} (OpenUSD)" if usd.get("path") else f"no scene.usda: {usd.get('reason')}")
             if physics is not None else None)]
    return "<table>" + "".join(f"<tr><th>{_e(k)}</th><td>{_e(v)}</td></tr>" for k, v in rows) + "</table>"


def _views(images: ReportImages) -> str:
    if not images.cameras:
        return '<p class="muted">no cameras</p>'
    rows = "".join(f"<tr><td>{_e(name)}</td><td>{_img(before, 'capture')}</td><td>{_img(after, 'converted')}</td></tr>"
                   for name, before, after in zip(images.cameras, images.before, images.after))
    return ("<table><tr><th>camera</th><th>before: the capture</th><th>after: the converted scene (t = 0)</th></tr>"
            + rows + "</table>")


def _checks(checks: tuple[Check, ...]) -> str:
    out = []
    for check in checks:
        css, mark = ("pass", "✔") if check.passed else ("fail", "✘") if check.passed is False else ("muted", "·")
        out.append(f'<span class="{css}">{mark} {_e(check.name)}</span> {_number(check.value)} '
                   f'<span class="muted">/ {_number(check.threshold)}</span>')
    return "<br>".join(out) or "—"


def _objects(manifest: Manifest, images: ReportImages) -> str:
    objects = manifest.get("objects", ())
    if not objects:
        return '<p class="muted">no object was constructed</p>'
    head = ("<tr><th></th><th>id</th><th>status</th><th>candidate</th><th>scores</th><th>checks (value / threshold)"
            "</th><th>drop test</th><th>mass, friction</th><th>reason</th></tr>")
    rows = []
    for entry in objects:
        scores = ", ".join(f"{_e(k)} {_number(v)}" for k, v in chosen_scores(entry).items()
                           if isinstance(v, (int, float)) and not isinstance(v, bool)) or "—"
        physics = "—" if entry.mass is None else (
            f"{_number(entry.mass)} kg, μ {_number(entry.friction)}<br>"
            f"{len(entry.collision)} convex parts")
        thumb = images.thumbnails.get(entry.id)
        rows.append(f"<tr><td>{_img(thumb, 'thumbnail') if thumb is not None else ''}</td><td>{_e(entry.id)}</td>"
                    f"<td class=\"status-{_e(str(entry.status))}\">{_e(status_words(entry))}</td>"
                    f"<td>{_e(candidate_name(entry))}</td><td>{scores}</td>"
                    f"<td>{_checks(entry.checks)}</td><td>{_e(drop_verdict(entry))}</td><td>{physics}</td>"
                    f"<td>{_e(entry.reason if not entry.accepted else '')}</td></tr>")
    return "<table>" + head + "".join(rows) + "</table>"


def _background(manifest: Manifest) -> str:
    b = manifest.background()
    if b is None:
        return '<p class="muted">the background stage did not run</p>'
    lines = [f"<p>{_e(b.source_gaussians)} Gaussians in the capture → {_e(b.gaussians)} in "
             f"<code>{_e(b.path)}</code>: {_e(b.removed)} removed with the objects, "
             f"{_e(b.filled)} filled in where they stood.</p>"]
    rows = []
    for obj in b.objects:
        removed = (obj.get("removed") or {}).get("union")
        disks = (obj.get("fill") or {}).get("disks")
        view = (obj.get("primary_view") or {}).get("name")
        rows.append(f"<tr><td>{_e(obj.get('id'))}</td><td>{_e(obj.get('status'))}</td><td class=num>{_e(removed)}</td>"
                    f"<td class=num>{_e(disks)}</td><td>{_e(view)}</td><td>{_e(obj.get('reason') or '')}</td></tr>")
    if rows:
        lines.append("<table><tr><th>object</th><th>status</th><th>removed</th><th>fill disks</th>"
                     "<th>target view</th><th>reason</th></tr>" + "".join(rows) + "</table>")
    return "".join(lines)


def _timings(manifest: Manifest) -> str:
    timings = manifest.timings.values
    rows = []
    for stage in dict.fromkeys(key.partition(".")[0] for key in timings):  # in the order they ran
        rows.append(f"<tr><th>{_e(stage)}</th><td class=num>{_number(timings.get(stage), 3)} s</td></tr>")
        rows += [f'<tr><td>&nbsp;&nbsp;{_e(key[len(stage) + 1:])}</td><td class=num>{_number(s, 3)} s</td></tr>'
                 for key, s in timings.items() if key.startswith(stage + ".")]
    return "<table>" + "".join(rows) + "</table>" if rows else '<p class="muted">no timings recorded</p>'


def _rollout(video: str | None, frames: list[np.ndarray]) -> str:
    if video is None and not frames:
        return ('<p class="muted">no rollout yet: <code>phirie simulate OUT_DIR</code> renders one (and adds it '
                "here)</p>")
    strip = "".join(_img(f, "frame", 0.5 if f.shape[1] > 200 else 1.0) for f in frames)
    # linked, not embedded: OpenCV writes MPEG-4 part 2 (mp4v), which browsers' players mostly refuse
    link = f'<p>video: <a href="{_e(video)}">{_e(video)}</a></p>' if video else ""
    return f'<div class="strip">{strip}</div>{link}'


def report_html(manifest: Manifest, images: ReportImages, video: str | None = None,
                frames: list[np.ndarray] = ()) -> str:
    """The page (module docstring). ``video``: the rollout's path relative to the report;
    ``frames``: rollout frames (uint8 RGB) to inline."""
    title = f"phirie: {Path(str((manifest.get('scene') or {}).get('path') or 'scene')).name}"
    sections = [("Summary", _summary(manifest)), ("Before and after", _views(images)),
                ("Objects", _objects(manifest, images)), ("Background", _background(manifest)),
                ("Rollout", _rollout(video, list(frames))), ("Timings", _timings(manifest))]
    body = "".join(f"<h2>{_e(name)}</h2>{content}" for name, content in sections)
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{_e(title)}</title>'
            f"<style>{STYLE}</style></head><body><h1>{_e(title)}</h1>{body}</body></html>\n")


def _strip(frames: list[np.ndarray], count: int) -> list[np.ndarray]:
    if not frames or count <= 0:
        return []
    return [frames[int(k)] for k in np.linspace(0, len(frames) - 1, min(count, len(frames))).round()]


def write_report(out_dir: str | Path, config: ReportConfig = ReportConfig(), source: GaussianSplatData | None = None,
                 video: str | Path | None = None, frames: list[np.ndarray] = ()) -> Path:
    """Render and write ``OUT/report.html`` (atomically) and record it in the manifest (``report``,
    timing ``report``). ``source``: the capture's Gaussians in the world frame, when at hand;
    ``video``/``frames``: a rollout (its video file, and its frames to inline). A rollout recorded
    by an earlier call is kept while its file exists."""
    out_dir = Path(out_dir)
    manifest = Manifest.load_or_create(out_dir)
    with manifest.timed("report"):
        record = manifest.get("report") or {}
        if video is not None:
            video = Path(os.path.relpath(Path(video).resolve(), out_dir.resolve())).as_posix()
        elif record.get("video") and (out_dir / record["video"]).is_file():
            video = record["video"]
        images = render_images(out_dir, config.views, config.width, config.thumbnail, config.background, source)
        manifest.set("report", {"path": layout.REPORT, "video": video})
        write_text(out_dir / layout.REPORT, report_html(manifest, images, video, _strip(list(frames),
                                                                                              config.filmstrip)))
    manifest.write()
    return out_dir / layout.REPORT
