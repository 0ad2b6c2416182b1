"""Scene folders: detect the layout and load one ``SceneInput``.

Layouts (docs/architecture.md "Contracts"; detected, never asked for):
- COLMAP: ``sparse/0/`` or ``sparse/`` (``.bin`` or ``.txt``), images in ``images/``.
- nerfstudio: ``transforms.json`` (OpenGL camera-to-world), images where its frames say.
- ScanNet++ DSLR: ``dslr/nerfstudio/transforms_undistorted.json`` with
  ``dslr/resized_undistorted_images/`` (else ``dslr/colmap/`` with ``dslr/resized_images/``),
  surface ``scans/mesh_aligned_0.05.ply``, annotations ``scans/segments_anno.json``.
- A Gaussian PLY on its own (no cameras).

Gaussians: ``--gaussians PATH``, else ``point_cloud.ply``, ``splat.ply``, or the highest
``point_cloud/iteration_*/point_cloud.ply``; degenerate ones (``gaussian_checks``) are dropped
with one warning line. Surface mesh: ``--surface PATH``, else the
ScanNet++ scan, else ``surface.{ply,obj}`` or ``mesh.{ply,obj}``. Instance masks:
``masks/<image stem>.png`` (16-bit, 0 = none, k = instance k). Candidates:
``candidates/<instance id>/<name>.{glb,obj,ply}``, each with an optional Gaussian PLY
beside it (any PLY whose header carries 3DGS fields, paired by name prefix).
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np

from phirie_jax.errors import SceneInputError
from phirie_jax.io.camera import refuse_link_outside
from phirie_jax.io.colmap import read_colmap_model
from phirie_jax.io.gaussian_checks import degenerate_counts, degenerate_mask, describe_counts
from phirie_jax.io.images import image_size
from phirie_jax.io.ply import is_gaussian_ply, read_gaussian_ply
from phirie_jax.io.transforms_json import read_transforms_json
from phirie_jax.types import GAUSSIAN_NAMES, Camera, CandidateFiles, GaussianSplatData, SceneInput

SURFACE_NAMES = ("surface.ply", "surface.obj", "mesh.ply", "mesh.obj")
MESH_SUFFIXES = (".glb", ".gltf", ".obj", ".ply")
SCANNETPP_MESH = Path("scans/mesh_aligned_0.05.ply")
SCANNETPP_SEGMENTS = Path("scans/segments_anno.json")


def find_gaussians(root: Path) -> Path | None:
    for name in GAUSSIAN_NAMES:
        if (root / name).is_file():
            return root / name
    iterations = []
    for p in root.glob("point_cloud/iteration_*/point_cloud.ply"):
        m = re.fullmatch(r"iteration_(\d+)", p.parent.name)
        if m:
            iterations.append((int(m.group(1)), p))
    return max(iterations)[1] if iterations else None


def load_gaussians(path: Path) -> GaussianSplatData:
    """The scene's Gaussians without the degenerate ones (``gaussian_checks``).

    Dropping them is announced by one line on stderr, ``phirie: warning: FILE: dropped N
    degenerate Gaussians (...)``; a file holding nothing else is a ``SceneInputError``.
    """
    data = read_gaussian_ply(path, allow_non_finite=True)
    bad = degenerate_mask(data)
    if not bad.any():
        return data
    counts = describe_counts(degenerate_counts(data))
    if bad.all():
        raise SceneInputError(path, "element vertex",
                              f"all {data.num} Gaussians are degenerate ({counts}); expected usable ones")
    print(f"phirie: warning: {path}: dropped {int(bad.sum())} degenerate Gaussians ({counts})",
          file=sys.stderr)
    return data.subset(~bad)


def _cameras(root: Path) -> tuple[str, list[Camera], Path | None, np.ndarray | None]:
    """(layout, cameras, the file they came from, sparse points) for a scene folder."""
    dslr = root / "dslr"
    undistorted = dslr / "nerfstudio" / "transforms_undistorted.json"
    if undistorted.is_file():
        cams = read_transforms_json(undistorted, image_root=dslr / "resized_undistorted_images", scene_root=root)
        return "scannetpp", cams, undistorted, None
    if (dslr / "colmap").is_dir():
        cams, pts = read_colmap_model(dslr / "colmap", image_dir=dslr / "resized_images", scene_root=root)
        images = next(p for p in (dslr / "colmap" / "images.bin", dslr / "colmap" / "images.txt") if p.is_file())
        return "scannetpp", cams, images, pts
    for sparse in (root / "sparse" / "0", root / "sparse"):
        if any((sparse / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
            cams, pts = read_colmap_model(sparse, image_dir=root / "images", scene_root=root)
            images = next(p for p in (sparse / "images.bin", sparse / "images.txt") if p.is_file())
            return "colmap", cams, images, pts
    if (root / "transforms.json").is_file():
        return ("nerfstudio", read_transforms_json(root / "transforms.json", scene_root=root),
                root / "transforms.json", None)
    return "gaussians", [], None, None


def _check_images(cameras: list[Camera], source: Path) -> None:
    for cam in cameras:
        if cam.image_path is None or not cam.image_path.is_file():
            raise SceneInputError(cam.image_path or source, f"camera '{cam.name}'",
                                  f"image file missing (listed in {source.name})")
        width, height = image_size(cam.image_path)
        if (width, height) != (cam.width, cam.height):
            raise SceneInputError(cam.image_path, "image size",
                                  f"{width}×{height} (expected {cam.width}×{cam.height} "
                                  f"from camera '{cam.name}' in {source.name})")


def _masks(root: Path, cameras: list[Camera]) -> tuple[Path | None, ...] | None:
    folder = root / "masks"
    if not folder.is_dir() or not cameras:
        return None
    masks = []
    for cam in cameras:
        path = folder / Path(cam.name).with_suffix(".png")
        if not path.is_file():
            masks.append(None)
            continue
        refuse_link_outside(path, root, path, "mask", str(path.relative_to(root)))
        width, height = image_size(path)
        if (width, height) != (cam.width, cam.height):
            raise SceneInputError(path, "mask size",
                                  f"{width}×{height} (expected {cam.width}×{cam.height} like camera '{cam.name}')")
        masks.append(path)
    return tuple(masks)


def find_candidates(folder: Path) -> dict[int, tuple[CandidateFiles, ...]]:
    """``candidates/<instance id>/``: meshes, each paired with a Gaussian PLY whose name starts like it."""
    found: dict[int, tuple[CandidateFiles, ...]] = {}
    if not folder.is_dir():
        return found
    for sub in sorted(p for p in folder.iterdir() if p.is_dir()):
        if not sub.name.isdigit():
            raise SceneInputError(sub, "candidate folder name",
                                  f"{sub.name!r} (expected the integer instance id, e.g. candidates/3/)")
        files = sorted(p for p in sub.iterdir() if p.suffix.lower() in MESH_SUFFIXES)
        splats = [p for p in files if p.suffix.lower() == ".ply" and is_gaussian_ply(p)]
        meshes = [p for p in files if p not in splats]
        entries = []
        for mesh in meshes:
            paired = [s for s in splats if s.stem.startswith(mesh.stem)]
            if not paired and len(meshes) == 1 and len(splats) == 1:
                paired = splats
            entries.append(CandidateFiles(int(sub.name), mesh.stem, mesh, paired[0] if paired else None))
        found[int(sub.name)] = tuple(entries)
    return found


def load_scene(
    path: str | Path,
    gaussians: str | Path | None = None,
    surface: str | Path | None = None,
    check_images: bool = True,
) -> SceneInput:
    """Detect the layout of ``path`` (a scene folder or a Gaussian PLY) and load it.

    Raises ``SceneInputError`` naming the file, the field and what was expected.
    """
    path = Path(path).resolve()
    if not path.exists():
        raise SceneInputError(path, None, "does not exist (expected a scene folder or a Gaussian PLY)")
    if path.is_file():
        if path.suffix.lower() != ".ply":
            raise SceneInputError(path, None, "not a folder or a .ply (expected a scene folder or a Gaussian PLY)")
        return SceneInput(root=path.parent, layout="gaussians",
                          gaussians=load_gaussians(path), gaussians_path=path)

    layout, cameras, source, points = _cameras(path)
    if check_images and cameras:
        _check_images(cameras, source)
    gaussians_path = Path(gaussians).resolve() if gaussians is not None else find_gaussians(path)
    if gaussians is not None and not gaussians_path.is_file():
        raise SceneInputError(gaussians_path, "--gaussians", "file not found")
    if surface is not None:
        surface_path = Path(surface).resolve()
        if not surface_path.is_file():
            raise SceneInputError(surface_path, "--surface", "file not found")
    else:
        options = [SCANNETPP_MESH, *SURFACE_NAMES]
        surface_path = next((path / p for p in options if (path / p).is_file()), None)
    segments = path / SCANNETPP_SEGMENTS
    return SceneInput(
        root=path,
        layout=layout,
        gaussians=load_gaussians(gaussians_path) if gaussians_path else None,
        gaussians_path=gaussians_path,
        cameras=tuple(cameras),
        camera_source=source,
        sparse_points=points,
        surface_mesh=surface_path,
        masks=_masks(path, cameras),
        candidates=find_candidates(path / "candidates"),
        segments_anno=segments if segments.is_file() else None,
    )
