"""Object candidates behind one interface: a mesh in its own canonical frame, optional
visual Gaussians, provenance — from external files or the built-in generators.

External candidates (``candidates/<instance id>/<name>.{glb,gltf,obj,ply}``, how TRELLIS,
ReconViaGen or SAM 3D outputs come in) have arbitrary frames: unknown up axis, unit-box
scale. They are registered by search. Built-in candidates are made from the observation
in the gravity frame, so their placement is known and they are only scored.

A candidate that cannot be made (unreadable file, no faces, a generator that fails on
this instance) is returned with ``error`` set; it is recorded and never ranked.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from phirie_jax.construct.objects.config import ObjectsConfig
from phirie_jax.construct.objects.generators import GENERATORS, GeneratorError, InstanceInput
from phirie_jax.types import CandidateFiles

MIN_AREA = 1e-12  # a mesh with less surface than this (in its own units²) cannot be sampled


@dataclasses.dataclass(frozen=True)
class Candidate:
    name: str                        # unique within an instance: "external:<stem>" or the generator
    generator: str                   # "external" | "visual_hull" | "primitive" | "extrude"
    priority: int                    # position in the pool (the fixed-priority order)
    vertices: np.ndarray | None      # (V, 3) canonical frame
    faces: np.ndarray | None         # (F, 3) int64
    placement: np.ndarray | None     # (4, 4) canonical → gravity frame, when known (built-ins)
    gaussians: Path | None = None    # visual Gaussians in the canonical frame, when brought
    source: str | None = None        # file it came from
    error: str | None = None         # why it could not be made
    info: dict = dataclasses.field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.error is None

    def to_trimesh(self):
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, process=False)

    def record(self) -> dict:
        return {"name": self.name, "generator": self.generator, "priority": self.priority,
                "source": self.source, "gaussians": None if self.gaussians is None else str(self.gaussians),
                "faces": None if self.faces is None else int(len(self.faces)), **self.info}


def mesh_problem(vertices: np.ndarray, faces: np.ndarray) -> str | None:
    """Why a mesh cannot be a candidate, or None."""
    if len(faces) == 0 or len(vertices) == 0:
        return "no triangles (expected a triangle mesh)"
    if not np.all(np.isfinite(vertices)):
        return "non-finite vertex coordinates"
    if faces.min() < 0 or faces.max() >= len(vertices):
        return "face indices out of range"
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    if not area > MIN_AREA:
        return f"zero surface area ({area:.3g})"
    return None


def load_external(files: CandidateFiles, priority: int) -> Candidate:
    """One external candidate; a broken file gives a candidate with ``error`` set."""
    import trimesh

    name = f"external:{files.name}"
    base = dict(name=name, generator="external", priority=priority, placement=None,
                gaussians=files.gaussians, source=str(files.mesh))
    try:
        mesh = trimesh.load(files.mesh, force="mesh", process=False)
        vertices = np.asarray(mesh.vertices, np.float64)
        faces = np.asarray(mesh.faces, np.int64).reshape(-1, 3)
    except Exception as err:  # noqa: BLE001 — trimesh raises many types for bad files; all mean "unreadable"
        return Candidate(vertices=None, faces=None, error=f"{files.mesh.name}: not a readable mesh "
                         f"({type(err).__name__}: {err})", **base)
    problem = mesh_problem(vertices, faces)
    if problem:
        return Candidate(vertices=None, faces=None, error=f"{files.mesh.name}: {problem}", **base)
    return Candidate(vertices=vertices, faces=faces, **base)


def builtin(generator: str, inst: InstanceInput, config: ObjectsConfig, priority: int) -> Candidate:
    base = dict(name=generator, generator=generator, priority=priority)
    try:
        shape = GENERATORS[generator](inst, config)
    except GeneratorError as err:
        return Candidate(vertices=None, faces=None, placement=None, error=str(err), **base)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError, OSError) as err:  # degenerate input
        return Candidate(vertices=None, faces=None, placement=None,
                         error=f"{generator} failed: {type(err).__name__}: {err}", **base)
    problem = mesh_problem(shape.vertices, shape.faces)
    if problem:
        return Candidate(vertices=None, faces=None, placement=None, error=problem, **base)
    return Candidate(vertices=shape.vertices, faces=shape.faces, placement=shape.placement, info=shape.info, **base)


def candidate_pool(inst: InstanceInput, external: tuple[CandidateFiles, ...], config: ObjectsConfig) -> list[Candidate]:
    """Every candidate of the configured pool, in priority order (duplicates skipped)."""
    out: list[Candidate] = []
    seen: set[str] = set()
    for entry in config.generators:
        if entry == "external" or entry.startswith("external:"):
            wanted = entry.partition(":")[2]
            for files in sorted(external, key=lambda f: f.name):
                if (not wanted or files.name == wanted) and f"external:{files.name}" not in seen:
                    seen.add(f"external:{files.name}")
                    out.append(load_external(files, len(out)))
        elif entry not in seen:
            seen.add(entry)
            out.append(builtin(entry, inst, config, len(out)))
    return out
