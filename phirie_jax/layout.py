"""Every name in an output folder, once (docs/architecture.md "Contracts": paths in the manifest are
relative to the output folder).

    OUT/manifest.json              the record every stage writes
    OUT/transforms.json            the capture's cameras (the folder is self-contained)
    OUT/observe/surface.ply        the splat-derived scene surface, when one was fused
    OUT/objects/<id>/mesh.obj      canonical completed mesh; the manifest's pose places it
    OUT/objects/<id>/visual.ply    the object's own Gaussians, canonical frame
    OUT/objects/<id>/collision/part_NN.obj   convex parts, canonical frame
    OUT/objects/<id>/object.urdf
    OUT/scene.xml                  MJCF of the whole scene
    OUT/scene.usda                 the same scene in OpenUSD (when pxr is importable)
    OUT/report.html                what the conversion made, self-contained (images inlined)
    OUT/background.ply             G_bg = (G0 \\ ∪R_i) ∪ G_fill
    OUT/background/targets/        the inpainting targets, when written
    OUT/.phirie.lock               the running conversion's lock (``io.output_folder``)
"""

from __future__ import annotations

from pathlib import Path

MANIFEST = "manifest.json"
CAMERAS = "transforms.json"
BACKGROUND_TARGETS = "background/targets"
OBSERVED_SURFACE = "observe/surface.ply"
SCENE_MJCF = "scene.xml"
SCENE_USD = "scene.usda"
REPORT = "report.html"
BACKGROUND = "background.ply"
OBJECTS = "objects"
OBJECT_MESH = "mesh.obj"
OBJECT_VISUAL = "visual.ply"
OBJECT_URDF = "object.urdf"
COLLISION = "collision"
LOCK = ".phirie.lock"

# The top-level names a run writes (``io.output_folder``: a folder holding one of them and no
# manifest of an earlier run is not an output folder).
TOP_LEVEL = (MANIFEST, CAMERAS, SCENE_MJCF, SCENE_USD, REPORT, BACKGROUND, OBJECTS, "observe", "background")


# The folders the stages write files into (globs, relative to the output folder): where an
# interrupted write may have left a temporary (``io.atomic.remove_temporaries``).
WRITTEN_FOLDERS = (".", "observe", f"{OBJECTS}/*", f"{OBJECTS}/*/{COLLISION}", "background", BACKGROUND_TARGETS)


def written_folders(out_dir: str | Path) -> list[Path]:
    """The existing folders of ``WRITTEN_FOLDERS`` in ``out_dir``."""
    out_dir = Path(out_dir)
    found = [out_dir / p for p in WRITTEN_FOLDERS if "*" not in p] + [
        match for p in WRITTEN_FOLDERS if "*" in p for match in sorted(out_dir.glob(p))]
    return [f for f in found if f.is_dir() and not f.is_symlink()]


def object_dir(object_id: int) -> Path:
    """``objects/<id>`` (relative to the output folder)."""
    return Path(OBJECTS) / str(object_id)


def object_file(object_id: int, name: str) -> str:
    """``objects/<id>/<name>`` as the manifest records it."""
    return (object_dir(object_id) / name).as_posix()


def collision_part(object_id: int, index: int) -> str:
    """``objects/<id>/collision/part_NN.obj`` as the manifest records it."""
    return (object_dir(object_id) / COLLISION / f"part_{index:02d}.obj").as_posix()


def resolve(out_dir: str | Path, path: str | Path) -> Path:
    """A manifest path (relative to ``out_dir``, or absolute) as a path to open."""
    path = Path(path)
    return path if path.is_absolute() else Path(out_dir) / path
