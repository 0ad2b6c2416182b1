"""The physics stage's config (collision, priors, export, drop tests): frozen dataclasses whose defaults are the φ-RIE paper's numbers.

Where the paper gives a number it is the default and the field says so ("paper");
every other default is ours and the field says why. Lengths are metres, angles degrees.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

from phirie_jax.errors import ConfigValueError
from phirie_jax.ranges import (
    AT_LEAST_ONE,
    NON_NEGATIVE,
    OPEN_FRACTION,
    POSITIVE,
    POSITIVE_FRACTION,
    Choice,
    Each,
    Positions,
    Range,
    at_least,
    at_most,
    check_ranges,
    shown,
)

DropBackend = Literal["auto", "mjx", "warp", "mujoco"]
Solver = Literal["newton", "cg"]
Merge = Literal["volume", "coacd"]
Jacobian = Literal["dense", "sparse"]
Preprocess = Literal["auto", "on", "off"]
SceneBackground = Literal["supports", "plane"]


@dataclasses.dataclass(frozen=True)
class DropTestConfig:
    """The drop test (paper protocol): each body alone on a plane, 240 Hz, settle then free.

    Spawned in its registered orientation with its lowest collision point on the plane;
    velocities zeroed after every settling step, then free motion. Stable if the centre of mass
    ends < ``max_drift`` from its spawn and no lower than ``min_final_height`` relative to the
    plane. Measurements behind the defaults: ``experiments/results/physics_notes.md``.

    Attributes:
        timestep: seconds per step (paper: 240 Hz).
        settle_time: velocity-zeroed settling (paper: 2 s).
        free_time: free motion after settling (paper: 2 s).
        max_drift: stable if the centre of mass drifts less than this (paper: 3 cm).
        min_final_height: ... and its final height above the plane is at least this (paper: −5 cm).
        backend: "mjx" (one vmapped program per batch), "warp" (MuJoCo Warp: one world per candidate,
            CUDA graphs; ``pip install phirie_jax[warp]``), "mujoco" (the C library, the reference) or
            "auto" (C on a CPU and for batches under ``droptest.AUTO_BATCH_MIN`` candidates, where no
            program compile pays; larger ones Warp if installed on a GPU, else MJX).
        solver / jacobian: MuJoCo's solver ("newton" or "cg") and mass-matrix layout ("dense" or
            "sparse"): Newton/dense is fastest for the same verdicts (physics_notes.md "Solver").
        solver_iterations / line_search_iterations / tolerance: ours, the fewest that keep the
            verdicts of MuJoCo's defaults in C and MJX (physics_notes.md "Solver limits").
        vertex_budget: vertices of every convex part, padded (static shape; ≤ 64 so MJX collides
            hulls cheaply; physics_notes.md "Static shapes").
        part_buckets: parts padded with ghost parts to the first bucket that holds them (one
            program per bucket; physics_notes.md "Static shapes").
        min_batch: candidates padded to a power of two, at least this (a second batch reuses the
            program; physics_notes.md "Static shapes").
        max_batch: larger batches run in chunks of this many (bounded memory).
        unroll: protocol steps per loop trip of the MJX program (1: more was no faster and compiled
            slower; physics_notes.md "Static shapes").
    """

    timestep: float = 1.0 / 240.0
    settle_time: float = 2.0
    free_time: float = 2.0
    max_drift: float = 0.03
    min_final_height: float = -0.05
    backend: DropBackend = "auto"
    solver: Solver = "newton"
    jacobian: Jacobian = "dense"
    solver_iterations: int = 4
    line_search_iterations: int = 4
    tolerance: float = 1e-6
    vertex_budget: int = 64
    part_buckets: tuple[int, ...] = (1, 4, 16)
    min_batch: int = 8
    max_batch: int = 4096
    unroll: int = 1

    def __post_init__(self):
        check_ranges(self, {
            "backend": Choice.of(DropBackend), "solver": Choice.of(Solver), "jacobian": Choice.of(Jacobian),
            "timestep": POSITIVE, "settle_time": NON_NEGATIVE, "free_time": NON_NEGATIVE, "max_drift": POSITIVE,
            "min_final_height": Range(), "solver_iterations": AT_LEAST_ONE, "line_search_iterations": AT_LEAST_ONE,
            "tolerance": NON_NEGATIVE, "vertex_budget": Range(4), "part_buckets": Each(AT_LEAST_ONE, increasing=True),
            "min_batch": AT_LEAST_ONE, "max_batch": at_least(self.min_batch, "min_batch"), "unroll": AT_LEAST_ONE})

    @property
    def settle_steps(self) -> int:
        return int(round(self.settle_time / self.timestep))

    @property
    def free_steps(self) -> int:
        return int(round(self.free_time / self.timestep))


@dataclasses.dataclass(frozen=True)
class AdaptiveCoacd:
    """CoACD's settings by the object's size and complexity (``collision.coacd_settings``).

    A completed mesh is a visual hull or a registered asset of up to 40K triangles whose surface
    carries small bumps; at a fixed threshold CoACD chases them, splitting a fruit into 16 parts
    in 19 s of CPU. Measurements behind the defaults: ``experiments/results/coacd_parts.json``.

    Attributes:
        enabled: False: the fixed settings of ``CoacdConfig`` for every object.
        max_triangles: CoACD decomposes the mesh simplified to this many triangles (the body's
            volume, and the parts' ratio to it, stay those of the repaired mesh).
        mcts_iterations: CoACD's tree-search iterations (the fixed ``CoacdConfig.mcts_iterations``: 60).
        resolution: CoACD's sampling resolution of its concavity measure (the fixed
            ``CoacdConfig.resolution``: 2000, CoACD's default); at half of it the concave objects
            decomposed 2–30 % faster (the slowest 21.0 → 19.0 s) with hull-volume ratios within
            0.013, and all 19 measured objects' drop tests stayed stable (``coacd_resolution.json``).
        tolerance: metres: an absolute concavity tolerance; CoACD's threshold is relative to the
            object's largest extent, so a small object's threshold is raised to ``2 · tolerance /
            extent`` (it stops at the same absolute detail as a large one).
        convex_solidity: a watertight mesh enclosing at least this fraction of its convex hull's
            volume is nearly convex ...
        convex_threshold: ... and decomposed at this threshold at least (its concavities are
            surface bumps, not handles or cavities).
        concave_threshold: any other object is decomposed at this threshold at least (default: the
            base ``CoacdConfig.threshold``, so no floor of its own). Raised, the concave objects
            decompose faster and coarser: at 0.1, 1.6× less CPU on 51 objects (the slowest 23.7 →
            13.9 s), but a captured figurine's parts changed enough for its drop test to fail and
            two mugs' hull-volume ratios rose by 0.12 (``coacd_concave_threshold.json``).
    """

    enabled: bool = True
    max_triangles: int = 8000
    mcts_iterations: int = 30
    resolution: int = 1000
    tolerance: float = 0.003
    convex_solidity: float = 0.85
    convex_threshold: float = 0.1
    concave_threshold: float = 0.05

    def __post_init__(self):
        check_ranges(self, {"max_triangles": Range(4), "mcts_iterations": AT_LEAST_ONE, "resolution": AT_LEAST_ONE,
                            "tolerance": NON_NEGATIVE, "convex_solidity": POSITIVE_FRACTION,
                            "convex_threshold": POSITIVE_FRACTION, "concave_threshold": POSITIVE_FRACTION})


@dataclasses.dataclass(frozen=True)
class CoacdConfig:
    """Convex decomposition by CoACD (``collision``): its own settings, seeded.

    Attributes:
        threshold: concavity threshold (issue: 0.05); ``PhysicsConfig.max_parts`` bounds the parts.
        preprocess: manifold remeshing: "auto" = only for a mesh repair could not close; "on" /
            "off" force it.
        preprocess_resolution / resolution / seed: CoACD's own settings (its defaults; seeded).
        mcts_nodes / mcts_iterations: CoACD's tree search, ours (10 / 60): faster with tighter
            hulls than its defaults (physics_notes.md "CoACD tree search").
        adaptive: the settings above adapted to each object's size and complexity
            (``AdaptiveCoacd``; its ``enabled`` False keeps them fixed).
        merge: how parts past ``PhysicsConfig.max_parts`` are merged: "volume" (ours: CoACD
            uncapped, then the pair whose joint hull fills the thinnest gap first,
            ``collision.merge_parts``; concave objects 1.1–1.8× faster) or "coacd" (CoACD's own
            merge by its sampled concavity).
        threads: OpenMP threads of each worker process (CoACD runs parts of its search in an
            OpenMP team, one thread per core unless told): 0 = twice the worker's share of the
            CPU cores (``PhysicsConfig.workers``; ``stage.OPENMP_OVERSUBSCRIPTION``), at least
            one. A scene's few concave objects decompose for tens of seconds after the quick ones
            are done; with two threads each they use the cores the quick ones left (a bowl on a
            2-core machine: 13.3–14.8 s alone on one thread, 9.0–10.0 s on two, the same parts).
            Idle threads sleep (``native.IsolatedPool``), so while every worker is busy the
            second thread costs little (two workers on two cores: 16.4–16.6 s against
            15.0–16.8 s on one thread).
        niceness: how much lower the worker processes' CPU priority is than the conversion's
            (Unix ``nice``; not part of the options' hash): the background stage runs beside
            them, and its host work gets the larger share of busy cores (about nine times a
            worker's at 10).
    """

    threshold: float = 0.05
    preprocess: Preprocess = "auto"
    preprocess_resolution: int = 50
    resolution: int = 2000
    mcts_nodes: int = 10
    mcts_iterations: int = 60
    seed: int = 0
    adaptive: AdaptiveCoacd = AdaptiveCoacd()
    merge: Merge = "volume"
    threads: int = 0
    niceness: int = 10

    def __post_init__(self):
        check_ranges(self, {
            "threshold": POSITIVE_FRACTION, "preprocess": Choice.of(Preprocess),
            "preprocess_resolution": AT_LEAST_ONE, "resolution": AT_LEAST_ONE, "mcts_nodes": AT_LEAST_ONE,
            "mcts_iterations": AT_LEAST_ONE, "seed": NON_NEGATIVE, "merge": Choice.of(Merge),
            "threads": Range(0, bound="0: twice the worker's share of the cores"),
            "niceness": Range(0, 19)})


@dataclasses.dataclass(frozen=True)
class PhysicsConfig:
    """Simulator assets: collision geometry, physics priors, MJCF/URDF export, drop tests.

    Measurements behind the defaults: ``experiments/results/physics_notes.md``.

    Attributes:
        mass: kg of an object nothing better is known of (paper: 0.3 kg); see ``priors``.
        category_masses: ((category, kg), ...): the mass of every object of a category.
        object_masses: ((object id, kg), ...): one object's mass (``--mass ID=KG``), first of all.
        friction: sliding friction coefficient (paper: 0.5); torsional/rolling stay MuJoCo's
            defaults (physics_notes.md "Friction and restitution").
        restitution: coefficient of restitution (paper: 0), as the solref damping ratio (0 is
            critical damping; physics_notes.md "Friction and restitution").
        contact_timeconst: solref time constant, s (MuJoCo's default, ≥ 2 × the 240 Hz step).
        solimp: MuJoCo's contact impedance (dmin, dmax, width, midpoint, power; its defaults).
        max_triangles: a mesh is simplified to at most this many triangles before convex
            decomposition (paper: 40K).
        max_parts: CoACD's part limit (issue: 16).
        max_hull_vertices: vertices per convex part (CoACD decimation, then ours; ≤ the drop
            test's vertex budget).
        coacd: the convex decomposition's settings (``CoacdConfig``).
        min_volume: a mesh whose convex hull encloses less than this (m³) has zero volume and
            fails (a flat sheet cannot be a rigid body).
        workers: processes building the objects' collision in parallel; 0: one per CPU core, 1: in
            this process (each runs ``coacd.threads`` OpenMP threads).
        background: "supports" (a box under each support the objects stand on, fitted to the
            scene surface, plus a floor plane) or "plane" (one plane at the lowest support).
        support_thickness: thickness of a support box, below its top face.
        scene_solver_iterations / scene_line_search_iterations: the Newton solver's limits written
            to ``scene.xml``, more than the drop test's (physics_notes.md "Scene solver limits").
        drop_test: the drop test's settings.
    """

    mass: float = 0.3
    category_masses: tuple[tuple[str, float], ...] = ()
    object_masses: tuple[tuple[int, float], ...] = ()
    friction: float = 0.5
    restitution: float = 0.0
    contact_timeconst: float = 0.02
    solimp: tuple[float, float, float, float, float] = (0.9, 0.95, 0.001, 0.5, 2.0)
    max_triangles: int = 40_000
    max_parts: int = 16
    max_hull_vertices: int = 64
    coacd: CoacdConfig = CoacdConfig()
    min_volume: float = 1e-9
    workers: int = 0
    background: SceneBackground = "supports"
    support_thickness: float = 0.04
    scene_solver_iterations: int = 20
    scene_line_search_iterations: int = 10
    drop_test: DropTestConfig = DropTestConfig()

    def __post_init__(self):
        largest_bucket = max(self.drop_test.part_buckets, default=1)  # empty: the drop test's own check says so
        check_ranges(self, {
            "mass": POSITIVE, "friction": NON_NEGATIVE, "restitution": Range(0, 1, high_open=True),
            "contact_timeconst": POSITIVE,
            # MuJoCo's solimp: dmin, dmax and midpoint in (0, 1), width > 0, power ≥ 1
            "solimp": Positions((OPEN_FRACTION, OPEN_FRACTION, POSITIVE, OPEN_FRACTION, AT_LEAST_ONE)),
            "max_triangles": Range(4),
            "max_parts": at_most(largest_bucket, "the largest of drop_test.part_buckets", low=1),
            "max_hull_vertices": at_most(self.drop_test.vertex_budget, "drop_test.vertex_budget", low=4),
            "min_volume": NON_NEGATIVE, "workers": Range(0, bound="0: one per CPU core"),
            "background": Choice.of(SceneBackground), "support_thickness": POSITIVE,
            "scene_solver_iterations": AT_LEAST_ONE, "scene_line_search_iterations": AT_LEAST_ONE})
        for category, mass in self.category_masses:
            if mass not in POSITIVE:
                raise ConfigValueError(type(self).__name__, "category_masses", f"{category} {shown(mass)}",
                                       f"a mass > 0 for {category!r}")
        for ident, mass in self.object_masses:
            if mass not in POSITIVE:
                raise ConfigValueError(type(self).__name__, "object_masses", f"{ident} {shown(mass)}",
                                       f"a mass > 0 for object {ident}")
