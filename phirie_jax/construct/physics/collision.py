"""Collision geometry of an asset: mesh repair, CoACD convex decomposition, hull decimation.

``repair_mesh`` merges vertices, drops degenerate and duplicate triangles, fixes winding and
normals, fills small holes and simplifies to the triangle budget; it raises ``MeshError``
(a reason for people) for an empty mesh, a non-manifold one (an edge shared by more than two
triangles) and one of zero volume. ``decompose`` runs CoACD (threshold 0.05, ≤ 16 parts; the
threshold raised for small and nearly convex objects, ``coacd_settings``; its parts past 16
merged by ``merge_parts``) and decimates each
part to ≤ 64 hull vertices so MJX can collide it; a CoACD failure falls back to the convex hull
and says so. ``hull_part`` is the fast single-hull stand-in used
while ranking candidates.

Every part is a convex point set in the mesh's own (canonical) frame: ``(V, 3)`` vertices,
V ≤ the vertex budget, with the hull's outward-wound triangles ``(F, 3)``.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from phirie_jax.construct.physics.config import PhysicsConfig
from phirie_jax.geometry import edge_keys

GHOST_SHRINK = 0.05   # a ghost part is its body's first part shrunk this much around its centroid


class MeshError(ValueError):
    """A mesh that cannot become a rigid body; the message is the reason."""


@dataclasses.dataclass(frozen=True)
class ConvexPart:
    vertices: np.ndarray   # (V, 3) float64 hull vertices
    faces: np.ndarray      # (F, 3) int64 outward-wound hull triangles

    @property
    def volume(self) -> float:
        v = self.vertices[self.faces]
        return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


@dataclasses.dataclass(frozen=True)
class RepairedMesh:
    vertices: np.ndarray   # (N, 3)
    faces: np.ndarray      # (M, 3)
    watertight: bool
    volume: float          # enclosed volume (watertight) or its convex hull's (open)
    report: dict           # what was changed


@dataclasses.dataclass(frozen=True)
class Collision:
    parts: tuple[ConvexPart, ...]
    report: dict           # method, parts, hull_volume_ratio, time_s, fallback reason, repair


def _trimesh(vertices, faces, process: bool = False):
    import trimesh

    return trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=process,
                           validate=False)


def _hull_volume(points: np.ndarray) -> float:
    return _hull(points)[1]


def _hull(points: np.ndarray) -> tuple[np.ndarray, float, float]:
    """The convex hull of ``points`` (P, 3): its vertices (V, 3), volume and area; a flat or too
    small set is its own vertices, of volume 0 (area 0)."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        if len(points) >= 4:
            hull = ConvexHull(points)
            return points[hull.vertices], float(hull.volume), float(hull.area)
    except (QhullError, ValueError):
        pass
    return points, 0.0, 0.0


def merge_parts(parts: list[np.ndarray], count: int) -> list[np.ndarray]:
    """Convex point sets (each (V_i, 3)) merged down to ``count``: each step joins the pair whose
    joint hull adds the least volume per unit of its area, i.e. the thinnest gap the merge fills
    (a depth, as CoACD's own merge measures concavity by a distance). Returns the hull vertices of
    every kept part; fewer than ``count`` parts come back as they are.

    CoACD's merge samples its concavity measure anew for every pair: on concave meshes it took
    8–26 s of a 22–36 s decomposition (47–65 parts to 16). This one costs a hull a pair, about a
    second, and keeps the hull-volume ratio within 0.1 of CoACD's merge, with the same drop-test
    verdicts (physics_notes.md "Merging CoACD's parts")."""
    if len(parts) <= count:
        return list(parts)
    hulls = [_hull(np.asarray(p, np.float64)) for p in parts]
    points = [h[0] for h in hulls]
    volumes = [h[1] for h in hulls]
    n = len(points)
    cost = np.full((n, n), np.inf)   # cost[i, j], i < j, of merging parts i and j

    def joint_cost(i: int, j: int) -> float:
        _, volume, area = _hull(np.concatenate([points[i], points[j]]))
        return (volume - volumes[i] - volumes[j]) / area if area > 0 else 0.0

    for i in range(n):
        for j in range(i + 1, n):
            cost[i, j] = joint_cost(i, j)
    alive = list(range(n))
    while len(alive) > count:
        i, j = np.unravel_index(int(np.argmin(cost)), cost.shape)
        points[i], volumes[i], _ = _hull(np.concatenate([points[i], points[j]]))
        alive.remove(j)
        cost[j, :] = cost[:, j] = np.inf
        for other in alive:
            if other != i:
                a, b = min(i, other), max(i, other)
                cost[a, b] = joint_cost(a, b)
    return [points[k] for k in alive]


def _simplify(mesh, max_triangles: int):
    """Quadric decimation (Open3D) down to ``max_triangles``."""
    import open3d as o3d

    o3 = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                   o3d.utility.Vector3iVector(mesh.faces))
    o3 = o3.simplify_quadric_decimation(target_number_of_triangles=int(max_triangles))
    o3.remove_degenerate_triangles()
    o3.remove_unreferenced_vertices()
    return _trimesh(np.asarray(o3.vertices), np.asarray(o3.triangles))


def orient_faces(faces: np.ndarray) -> np.ndarray:
    """Flip triangles so that every edge shared by two of them is traversed in opposite directions
    (breadth-first over edge neighbours, per connected piece; manifold input). A mesh whose
    triangles already agree (no directed edge twice: a marching-cubes visual hull) is returned as
    it is, without the walk: the walk would flip nothing."""
    faces = np.asarray(faces, np.int64).copy()
    count = int(faces.max()) + 1 if len(faces) else 0
    directed_edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    if len(np.unique(edge_keys(directed_edges, count))) == len(directed_edges):
        return faces
    edges = np.sort(np.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], 1).reshape(-1, 2), axis=1)
    _, edge_id = np.unique(edge_keys(edges, count), return_inverse=True)
    edge_id = edge_id.reshape(-1)
    order = np.argsort(edge_id, kind="stable")
    pairs = order.reshape(-1) // 3
    owners: dict[int, list[int]] = {}
    for e, f in zip(edge_id[order], pairs):
        owners.setdefault(int(e), []).append(int(f))
    neighbours: list[list[int]] = [[] for _ in range(len(faces))]
    for fs in owners.values():
        if len(fs) == 2:
            neighbours[fs[0]].append(fs[1])
            neighbours[fs[1]].append(fs[0])
    directed = lambda f: {(faces[f, i], faces[f, (i + 1) % 3]) for i in range(3)}  # noqa: E731
    seen = np.zeros(len(faces), bool)
    for root in range(len(faces)):
        if seen[root]:
            continue
        seen[root] = True
        queue = [root]
        while queue:
            f = queue.pop()
            mine = directed(f)
            for g in neighbours[f]:
                if seen[g]:
                    continue
                if mine & directed(g):          # same direction on the shared edge: flip g
                    faces[g] = faces[g, ::-1]
                seen[g] = True
                queue.append(g)
    return faces


def fill_holes(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Close each simple boundary loop of a consistently oriented mesh with a fan around its centroid."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    present = {tuple(e) for e in directed.tolist()}
    boundary = [(a, b) for a, b in directed.tolist() if (b, a) not in present]
    nxt: dict[int, int] = {}
    for a, b in boundary:
        if a in nxt:                             # a vertex on two holes: leave it open
            return vertices, faces
        nxt[a] = b
    new_v, new_f = [vertices], [faces]
    count = len(vertices)
    while nxt:
        start, loop = next(iter(nxt)), []
        v = start
        while v in nxt:
            loop.append(v)
            v = nxt.pop(v)
        if v != start or len(loop) < 3:
            continue
        centre = vertices[loop].mean(0)
        new_v.append(centre[None])
        # boundary edges run a→b on the existing side, so the patch runs b→a
        new_f.append(np.array([[loop[(i + 1) % len(loop)], loop[i], count] for i in range(len(loop))]))
        count += 1
    return np.concatenate(new_v), np.concatenate(new_f)


def repair_mesh(vertices: np.ndarray, faces: np.ndarray, config: PhysicsConfig = PhysicsConfig()) -> RepairedMesh:
    """A clean, consistently wound mesh of at most ``config.max_triangles`` triangles (or ``MeshError``)."""
    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    if len(vertices) == 0 or len(faces) == 0:
        raise MeshError(f"empty mesh ({len(vertices)} vertices, {len(faces)} triangles)")
    if not np.isfinite(vertices).all():
        raise MeshError("mesh has non-finite vertex coordinates")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(f"mesh triangles index vertices outside 0..{len(vertices) - 1}")
    report = {"input_vertices": len(vertices), "input_triangles": len(faces)}
    mesh = _trimesh(vertices, faces)
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        raise MeshError("empty mesh: every triangle is degenerate")
    _, counts = np.unique(edge_keys(mesh.edges_sorted, len(mesh.vertices)), return_counts=True)
    shared = int((counts > 2).sum())
    if shared:
        raise MeshError(f"non-manifold mesh: {shared} edges are shared by more than two triangles")
    hull = _hull_volume(mesh.vertices)
    if hull < config.min_volume:
        raise MeshError(f"zero volume: the convex hull encloses {hull:.3g} m³ (< min_volume {config.min_volume:g})")
    mesh = _trimesh(mesh.vertices, orient_faces(mesh.faces))
    if not mesh.is_watertight:
        mesh = _trimesh(*fill_holes(mesh.vertices, mesh.faces))
        report["holes_filled"] = bool(mesh.is_watertight)
    watertight = bool(mesh.is_watertight)
    if watertight and mesh.volume < 0:            # consistently wound, but inside out
        mesh = _trimesh(mesh.vertices, mesh.faces[:, ::-1])
    if len(mesh.faces) > config.max_triangles:
        mesh = _simplify(mesh, config.max_triangles)
        report["simplified_to"] = len(mesh.faces)
        watertight = bool(mesh.is_watertight)
    volume = abs(float(mesh.volume)) if watertight else hull
    if volume < config.min_volume:
        raise MeshError(f"zero volume: the mesh encloses {volume:.3g} m³ (< min_volume {config.min_volume:g})")
    report.update(vertices=len(mesh.vertices), triangles=len(mesh.faces), watertight=watertight)
    return RepairedMesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), watertight, volume, report)


def _farthest_points(points: np.ndarray, count: int) -> np.ndarray:
    """Indices of ``count`` points: the 6 axis extremes first, then farthest-point sampling."""
    chosen = list(dict.fromkeys(int(i) for i in np.concatenate([points.argmin(0), points.argmax(0)])))[:count]
    dist = np.min(np.linalg.norm(points[:, None] - points[chosen][None], axis=-1), axis=1)
    while len(chosen) < count:
        i = int(dist.argmax())
        chosen.append(i)
        dist = np.minimum(dist, np.linalg.norm(points - points[i], axis=1))
    return np.asarray(chosen)


def convex_part(points: np.ndarray, max_vertices: int) -> ConvexPart | None:
    """The convex hull of ``points`` with at most ``max_vertices`` vertices (None if it is flat).

    A hull with more vertices keeps a farthest-point subset of them (its hull lies inside the
    original, so the part never grows)."""
    from scipy.spatial import ConvexHull, QhullError

    points = np.asarray(points, np.float64)
    try:
        hull = ConvexHull(points)
        verts = points[hull.vertices]
        if len(verts) > max_vertices:
            verts = verts[_farthest_points(verts, max_vertices)]
            hull = ConvexHull(verts)
            verts = verts[hull.vertices]
        hull = ConvexHull(verts)
    except (QhullError, ValueError):
        return None
    faces = hull.simplices.copy()
    # wind outward: the normal points away from the centroid
    centre = verts.mean(0)
    tri = verts[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    flip = np.einsum("ij,ij->i", normal, tri[:, 0] - centre) < 0
    faces[flip] = faces[flip][:, ::-1]
    part = ConvexPart(verts, faces.astype(np.int64))
    return part if part.volume > 0 else None


def hull_part(vertices: np.ndarray, max_vertices: int = 64) -> ConvexPart:
    """The single convex-hull stand-in of a mesh (``MeshError`` when it is flat or empty)."""
    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    if len(vertices) < 4 or not np.isfinite(vertices).all():
        raise MeshError(f"no solid convex hull from {len(vertices)} vertices")
    part = convex_part(vertices, max_vertices)
    if part is None:
        raise MeshError("zero volume: the convex hull is flat")
    return part


def ghost_part(first: ConvexPart) -> ConvexPart:
    """A tiny copy of ``first`` strictly inside it (pads a body to its part bucket; never touches)."""
    centre = first.vertices.mean(0)
    return ConvexPart(centre + GHOST_SHRINK * (first.vertices - centre), first.faces)


@dataclasses.dataclass(frozen=True)
class CoacdSettings:
    """CoACD's settings for one mesh (``coacd_settings``) and the measures they came from."""

    threshold: float
    mcts_iterations: int
    resolution: int      # CoACD's sampling resolution of its concavity measure
    max_triangles: int   # CoACD's input simplified to at most this many triangles (0: as repaired)
    tier: str            # "fixed" (adaptive settings off), "nearly convex" or "concave"
    solidity: float      # mesh volume / convex hull volume (1 for an open mesh: unknown)
    extent: float        # the mesh's largest extent, metres

    def record(self) -> dict:
        return {"threshold": round(self.threshold, 4), "mcts_iterations": self.mcts_iterations,
                "resolution": self.resolution,
                "max_triangles": self.max_triangles, "tier": self.tier, "solidity": round(self.solidity, 4),
                "extent_m": round(self.extent, 4)}


def coacd_settings(mesh: RepairedMesh, config: PhysicsConfig = PhysicsConfig()) -> CoacdSettings:
    """CoACD's settings for ``mesh`` (``AdaptiveCoacd``): its threshold raised for a small object (an
    absolute tolerance) and to its tier's floor (nearly convex or concave), fewer tree-search
    iterations, a simplified input, a coarser concavity sampling; the fixed ``CoacdConfig`` settings
    when adaptation is off."""
    coacd = config.coacd
    adaptive = coacd.adaptive
    hull = _hull_volume(mesh.vertices)
    solidity = min(1.0, mesh.volume / hull) if mesh.watertight and hull > 0 else 1.0
    extent = float(np.max(mesh.vertices.max(0) - mesh.vertices.min(0)))
    if not adaptive.enabled:
        return CoacdSettings(coacd.threshold, coacd.mcts_iterations, coacd.resolution, 0, "fixed", solidity, extent)
    threshold = max(coacd.threshold, min(1.0, 2 * adaptive.tolerance / max(extent, 1e-9)))
    convex = mesh.watertight and solidity >= adaptive.convex_solidity
    threshold = max(threshold, adaptive.convex_threshold if convex else adaptive.concave_threshold)
    return CoacdSettings(threshold, adaptive.mcts_iterations, adaptive.resolution, adaptive.max_triangles,
                         "nearly convex" if convex else "concave", solidity, extent)


def _coacd_input(mesh: RepairedMesh, max_triangles: int) -> RepairedMesh:
    """The mesh CoACD decomposes: ``mesh``, simplified to ``max_triangles`` when it has more."""
    if not max_triangles or len(mesh.faces) <= max_triangles:
        return mesh
    small = _simplify(_trimesh(mesh.vertices, mesh.faces), max_triangles)
    watertight = bool(small.is_watertight)
    return RepairedMesh(np.asarray(small.vertices), np.asarray(small.faces), watertight,
                        abs(float(small.volume)) if watertight else mesh.volume, mesh.report)


def _coacd_parts(mesh: RepairedMesh, config: PhysicsConfig, settings: CoacdSettings | None = None) -> list[np.ndarray]:
    import coacd

    settings = settings or coacd_settings(mesh, config)
    coacd.set_log_level("error")
    preprocess = config.coacd.preprocess
    if preprocess == "auto":
        # CoACD's manifold remeshing closes what hole filling could not; a watertight mesh
        # skips it (CoACD's own "auto" remeshes self-intersecting closed meshes such as a mug
        # whose handle enters its wall: 169 s → 20 s, with tighter hulls, measured)
        preprocess = "off" if mesh.watertight else "on"
    ours = config.coacd.merge == "volume"   # CoACD uncapped, then merge_parts
    result = coacd.run_coacd(
        coacd.Mesh(mesh.vertices, mesh.faces), threshold=settings.threshold,
        max_convex_hull=-1 if ours else config.max_parts,
        preprocess_mode=preprocess, preprocess_resolution=config.coacd.preprocess_resolution,
        resolution=settings.resolution, mcts_nodes=config.coacd.mcts_nodes,
        mcts_iterations=settings.mcts_iterations, decimate=True, max_ch_vertex=config.max_hull_vertices,
        seed=config.coacd.seed)
    parts = [np.asarray(v, np.float64) for v, _ in result]
    return merge_parts(parts, config.max_parts) if ours else parts


def decompose(mesh: RepairedMesh, config: PhysicsConfig = PhysicsConfig()) -> Collision:
    """CoACD parts of a repaired mesh, each ≤ ``max_hull_vertices``, with the object's settings
    (``coacd_settings``, recorded under ``coacd``); the hull if CoACD fails."""
    start = time.perf_counter()
    report: dict = {"method": "coacd", "repair": mesh.report}
    parts: list[ConvexPart] = []
    settings = coacd_settings(mesh, config)
    report["coacd"] = settings.record()
    try:
        raw = _coacd_parts(_coacd_input(mesh, settings.max_triangles), config, settings)
        parts = [p for p in (convex_part(v, config.max_hull_vertices) for v in raw if len(v) >= 4) if p is not None]
        if not parts:
            raise RuntimeError(f"CoACD returned {len(raw)} parts, none a solid hull")
        if len(parts) > config.max_parts:   # CoACD's merge keeps to the limit; guard anyway
            parts = sorted(parts, key=lambda p: -p.volume)[: config.max_parts]
            report["parts_dropped"] = len(raw) - config.max_parts
    except Exception as err:  # noqa: BLE001 — any CoACD failure falls back to the hull, recorded
        parts = [hull_part(mesh.vertices, config.max_hull_vertices)]
        report.update(method="convex_hull", fallback=f"CoACD failed: {type(err).__name__}: {err}")
    hull_volume = sum(p.volume for p in parts)
    report.update(parts=len(parts), hull_vertices=[len(p.vertices) for p in parts],
                  hull_volume_ratio=hull_volume / mesh.volume, mesh_volume=mesh.volume,
                  time_s=time.perf_counter() - start)
    return Collision(tuple(parts), report)


def collision_from_mesh(vertices: np.ndarray, faces: np.ndarray, config: PhysicsConfig = PhysicsConfig()) -> Collision:
    """Repair then decompose (``MeshError`` for a mesh that cannot be a rigid body)."""
    start = time.perf_counter()
    collision = decompose(repair_mesh(vertices, faces, config), config)
    collision.report["total_time_s"] = time.perf_counter() - start
    return collision
