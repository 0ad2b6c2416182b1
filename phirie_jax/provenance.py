"""What a conversion was made from: the manifest's ``inputs`` record.

``inputs_record`` hashes the content of every file a conversion reads from the capture (each
regular file at the top of the scene folder, where the Gaussians, cameras and the scene's own
``frame.json`` and ``prompts.json`` live; the images, masks, COLMAP model, candidates and
annotations below it; an outside masks or targets folder) and, separately, the options that decide
the outputs (the convert config, the frame options, the mask source, the stages run, the
version). ``run_convert`` writes it as it starts; ``up_to_date`` tells whether a folder already
holds a complete conversion of the same inputs with the same options (``phirie convert-many``
skips such a scene on a re-run).

    {"inputs": "sha256:…", "options": "sha256:…", "files": 31, "bytes": 1234567}

Files are named relative to the scene folder when inside it, so a capture moved elsewhere keeps
its hash; renaming, adding or changing a file that is read changes it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from phirie_jax.layout import MANIFEST
from phirie_jax.manifest import Manifest
from phirie_jax.types import SceneInput

SECTION = "inputs"
CHUNK = 1 << 20


def _files_under(path: Path) -> list[Path]:
    """``path`` itself (a file), or every regular file below it (a folder), links followed."""
    if path.is_file():
        return [path]
    if not path.is_dir():
        return []
    return [Path(folder) / name for folder, _, names in os.walk(path, followlinks=True) for name in names
            if (Path(folder) / name).is_file()]


def read_paths(scene: SceneInput, extra: Iterable[Path | None] = ()) -> list[Path]:
    """Every file a conversion of ``scene`` reads: the regular files at the top of the scene folder,
    the Gaussians, surface, cameras, images, masks, candidates and annotations wherever they are,
    and ``extra`` (files or folders: an outside masks or targets folder)."""
    root = Path(scene.root)
    paths = [p for p in root.iterdir() if p.is_file()] if root.is_dir() else []
    named = [scene.gaussians_path, scene.surface_mesh, scene.camera_source, scene.segments_anno,
             *(c.image_path for c in scene.cameras), *(scene.masks or ()),
             *(p for group in scene.candidates.values() for c in group for p in (c.mesh, c.gaussians)), *extra]
    for path in named:
        if path is not None:
            paths += _files_under(Path(path))
    return sorted(set(paths), key=lambda p: _name(p, root))


def _name(path: Path, root: Path) -> str:
    path = Path(os.path.abspath(path))
    try:
        return path.relative_to(Path(os.path.abspath(root))).as_posix()
    except ValueError:
        return path.as_posix()


def _file_digest(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def _plain(value: Any) -> Any:
    """A config (nested dataclasses, tuples, paths) as JSON values, for a stable hash."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return str(value)


def options_hash(**options: Any) -> str:
    """``sha256:…`` of the options (configs, strings, tuples) as canonical JSON."""
    text = json.dumps(_plain(options), sort_keys=True, separators=(",", ":"))
    return "sha256:" + hashlib.sha256(text.encode()).hexdigest()


def inputs_record(scene: SceneInput, options: dict[str, Any], extra: Iterable[Path | None] = ()) -> dict:
    """The ``inputs`` record of a conversion of ``scene`` with ``options`` (module docstring)."""
    digest = hashlib.sha256()
    paths = read_paths(scene, extra)
    size = 0
    for path in paths:
        digest.update(f"{_name(path, scene.root)}\0{_file_digest(path)}\n".encode())
        size += path.stat().st_size
    return {"inputs": "sha256:" + digest.hexdigest(), "options": options_hash(version=_version(), **options),
            "files": len(paths), "bytes": size}


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("phirie_jax")
    except PackageNotFoundError:
        return "unknown"


def same_inputs(recorded: dict | None, record: dict) -> bool:
    """Whether a manifest's ``inputs`` record names the same inputs and options as ``record``."""
    return isinstance(recorded, dict) and all(recorded.get(k) == record[k] for k in ("inputs", "options"))


def up_to_date(out_dir: Path, record: dict) -> bool:
    """Whether ``out_dir`` holds a conversion whose every stage completed, made from the same inputs
    with the same options as ``record``."""
    if not (Path(out_dir) / MANIFEST).is_file():
        return False
    manifest = Manifest.load_or_create(out_dir)
    return not manifest.unfinished() and not manifest.get("failed_stage") and same_inputs(
        manifest.get(SECTION), record)
