"""Collision part files: ``objects/<id>/collision/part_NN.obj`` (``layout.collision_part``), written
and read here only.

Each file is one convex part in the canonical mesh frame (docs/architecture.md "Contracts"), unscaled, in
metres: its hull vertices and outward-wound triangles, 9 significant digits. The physics stage
reads the parts back after writing them, so the mass properties, ``scene.xml``, ``object.urdf``
and the drop test all use the values as written.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from phirie_jax import layout
from phirie_jax.construct.physics.collision import ConvexPart
from phirie_jax.io.atomic import write_files


def obj_text(part: ConvexPart) -> str:
    """The OBJ text of one part (vertices (V, 3), triangles (F, 3), 1-based)."""
    lines = [f"# phirie convex collision part: {len(part.vertices)} vertices, canonical frame, metres\n"]
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in part.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in part.faces]
    return "".join(lines)


def write_parts(out_dir: Path, object_id: int, parts: tuple[ConvexPart, ...]) -> list[str]:
    """Write every part of one object (all written, then renamed; stale part files removed);
    returns their paths relative to ``out_dir``, as the manifest records them."""
    paths = [layout.collision_part(object_id, k) for k in range(len(parts))]
    folder = out_dir / layout.object_dir(object_id) / layout.COLLISION
    names = [Path(p).name for p in paths]
    stale_pattern = Path(layout.collision_part(object_id, 0)).name.replace("00", "*")
    for stale in folder.glob(stale_pattern) if folder.is_dir() else ():
        if stale.name not in names:
            stale.unlink()
    write_files(folder, {n: obj_text(p).encode("ascii") for n, p in zip(names, parts)})
    return paths


def read_part(path: Path) -> ConvexPart:
    """A collision part OBJ back: vertices (V, 3) float64 and triangles (F, 3) int64."""
    verts, faces = [], []
    for line in Path(path).read_text(encoding="ascii").splitlines():
        if line.startswith("v "):
            verts.append([float(x) for x in line.split()[1:4]])
        elif line.startswith("f "):
            faces.append([int(tok.split("/")[0]) - 1 for tok in line.split()[1:4]])
    return ConvexPart(np.asarray(verts, np.float64).reshape(-1, 3), np.asarray(faces, np.int64).reshape(-1, 3))
