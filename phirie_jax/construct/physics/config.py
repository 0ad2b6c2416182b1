"""The physics stage's config (collision, priors, export, drop tests): frozen dataclasses whose defaults are the φ-RIE paper's numbers.

Where the paper gives a number it is the default and the field says so ("paper");
every other default is ours and the field says why. Lengths are metres, angles degrees.
"""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class DropTestConfig:
    """The drop test (paper protocol): each body alone on a plane, 240 Hz, settle then free.

    Spawned in its registered orientation with its lowest collision point on the plane (the
    paper's code spawned with interpenetration; we do not). During settling the velocities
    are zeroed after every step, so the body slides quasi-statically into a rest pose; then it
    moves freely. Stable if the centre of mass (PyBullet's base frame, what the paper's code
    reads) ends < ``max_drift`` from where it was spawned and no lower than ``min_final_height``
    relative to the plane.

    Attributes:
        timestep: seconds per step (paper: 240 Hz).
        settle_time: velocity-zeroed settling (paper: 2 s).
        free_time: free motion after settling (paper: 2 s).
        max_drift: stable if the centre of mass drifts less than this (paper: 3 cm).
        min_final_height: ... and its final height above the plane is at least this (paper: −5 cm).
        backend: "mjx" (every body of a batch in one vmapped, jitted program), "mujoco" (the C
            library, one body after another; the reference) or "auto": MJX when JAX has an
            accelerator, else the C library. Measured on a 2-core CPU
            (``experiments/results/bench_droptest_cpu.json``): C 100K steps/s, MJX 50K steps/s
            plus ~15 s of compilation per part bucket, so a CPU uses C.
        solver / jacobian: MuJoCo's constraint solver ("newton" or "cg") and mass-matrix layout
            ("dense" or "sparse"), the same for both backends. Measured on an H100
            (``experiments/results/droptest_tuning_h100_solvers.json``): CG takes 2–3× longer for
            the same verdicts, and the sparse layout (no cuSOLVER calls in MJX) is no faster.
        solver_iterations / line_search_iterations / tolerance: ours — the Newton solver's limits,
            the same for both backends. MJX's step is latency-bound on a GPU and each solver
            iteration adds sequential loop trips, so this is the largest lever there
            (``experiments/results/droptest_tuning_h100.json``, 1024 candidates): 0.70 s with
            (4, 4) against 1.06 s with (20, 10). MuJoCo C with (4, 4) gives the same verdicts as
            with MuJoCo's defaults (100, 50, 1e-8) on all 1024 cases of the benchmark set (drifts
            within 42 nm median); MJX agrees with C on all of them and on 99.2 % of the hard set.
            Fewer is not safe in MJX: with 2 iterations 5 of 1024 diverged and 85.5 % of the hard
            set agreed; its single-iteration path takes a 0/0 line-search step when the warm
            start is already optimal.
        vertex_budget: vertices of every convex part, padded (static shape; ≤ 64 so MJX collides
            hulls cheaply). Hulls with more vertices are decimated first.
        part_buckets: a body's convex parts are padded to the first bucket that holds them with
            "ghost" parts inside its first part (static shapes: one program per bucket).
        min_batch: candidates are padded to a power of two, at least this (static shapes: a
            second batch of the same bucket reuses the compiled program).
        max_batch: larger batches run in chunks of this many (bounded memory).
        unroll: protocol steps per loop trip of the MJX program (1: on an H100, 4 was no faster
            and compiled 2.5× slower).
    """

    timestep: float = 1.0 / 240.0
    settle_time: float = 2.0
    free_time: float = 2.0
    max_drift: float = 0.03
    min_final_height: float = -0.05
    backend: str = "auto"
    solver: str = "newton"
    jacobian: str = "dense"
    solver_iterations: int = 4
    line_search_iterations: int = 4
    tolerance: float = 1e-6
    vertex_budget: int = 64
    part_buckets: tuple[int, ...] = (1, 4, 16)
    min_batch: int = 8
    max_batch: int = 4096
    unroll: int = 1

    def __post_init__(self):
        if self.backend not in ("auto", "mjx", "mujoco"):
            raise ValueError(f"drop test backend {self.backend!r} (expected 'auto', 'mjx' or 'mujoco')")
        if not (self.timestep > 0 and self.settle_time >= 0 and self.free_time >= 0):
            raise ValueError("drop test: need timestep > 0 and non-negative settle/free times")
        if self.vertex_budget < 4 or not self.part_buckets or sorted(self.part_buckets) != list(self.part_buckets):
            raise ValueError("drop test: need vertex_budget ≥ 4 and increasing part_buckets")
        if self.solver not in ("newton", "cg") or self.jacobian not in ("dense", "sparse"):
            raise ValueError(f"drop test solver {self.solver!r} / jacobian {self.jacobian!r} "
                             "(expected 'newton' or 'cg' / 'dense' or 'sparse')")

    @property
    def settle_steps(self) -> int:
        return int(round(self.settle_time / self.timestep))

    @property
    def free_steps(self) -> int:
        return int(round(self.free_time / self.timestep))


@dataclasses.dataclass(frozen=True)
class PhysicsConfig:
    """Simulator assets: collision geometry, physics priors, MJCF/URDF export, drop tests.

    Attributes:
        mass: kg per object unless ``category_masses`` names its category (paper: 0.3 kg).
        category_masses: ((category, kg), ...) overrides of ``mass`` by instance category.
        friction: sliding friction coefficient (paper: 0.5); torsional/rolling stay MuJoCo's
            defaults (0.005, 0.0001).
        restitution: coefficient of restitution (paper: 0). MuJoCo has no restitution; its
            contact is a damped spring reaching its reference in ``contact_timeconst`` with
            damping ratio ζ, and a linear damped spring rebounds with e = exp(−πζ/√(1−ζ²)), so
            ζ = −ln e / √(π² + ln² e): restitution 0 is ζ = 1, critical damping (solref
            ``(timeconst, 1)``).
        contact_timeconst: solref time constant, s (MuJoCo's default 0.02 ≥ 2 × the 240 Hz step).
        solimp: MuJoCo's contact impedance (dmin, dmax, width, midpoint, power; its defaults).
        max_triangles: a mesh is simplified to at most this many triangles before convex
            decomposition (paper: 40K).
        coacd_threshold / max_parts: CoACD concavity threshold and part limit (issue: 0.05, 16).
        max_hull_vertices: vertices per convex part (CoACD decimation, then ours; ≤ the drop
            test's vertex budget).
        coacd_preprocess: CoACD's manifold remeshing: "auto" = only for a mesh repair could not
            close; "on" / "off" force it.
        coacd_preprocess_resolution / coacd_resolution / coacd_seed: CoACD's own settings (its
            defaults; seeded).
        coacd_mcts_nodes / coacd_mcts_iterations: CoACD's tree search (its defaults 20 / 150). Ours,
            10 / 60, measured on the synthetic mug and bowl: 1.8× and 1.3× faster with hull volume
            ratios 1.15 / 1.52 instead of 1.22 / 1.60.
        min_volume: a mesh whose convex hull encloses less than this (m³) has zero volume and
            fails (a flat sheet cannot be a rigid body).
        workers: processes building the objects' collision in parallel (CoACD is single-threaded);
            0: one per CPU core, 1: in this process.
        background: "supports" (a box under each support the objects stand on, fitted to the
            scene surface, plus a floor plane) or "plane" (one plane at the lowest support).
        support_thickness: thickness of a support box, below its top face.
        scene_solver_iterations / scene_line_search_iterations: the Newton solver's limits written
            to ``scene.xml`` (several objects in contact converge more slowly than one body on a
            plane, so the scene does not take the drop test's).
        drop_test: the drop test's settings.
    """

    mass: float = 0.3
    category_masses: tuple[tuple[str, float], ...] = ()
    friction: float = 0.5
    restitution: float = 0.0
    contact_timeconst: float = 0.02
    solimp: tuple[float, float, float, float, float] = (0.9, 0.95, 0.001, 0.5, 2.0)
    max_triangles: int = 40_000
    coacd_threshold: float = 0.05
    max_parts: int = 16
    max_hull_vertices: int = 64
    coacd_preprocess: str = "auto"
    coacd_preprocess_resolution: int = 50
    coacd_resolution: int = 2000
    coacd_mcts_nodes: int = 10
    coacd_mcts_iterations: int = 60
    coacd_seed: int = 0
    min_volume: float = 1e-9
    workers: int = 0
    background: str = "supports"
    support_thickness: float = 0.04
    scene_solver_iterations: int = 20
    scene_line_search_iterations: int = 10
    drop_test: DropTestConfig = DropTestConfig()

    def __post_init__(self):
        if self.background not in ("supports", "plane"):
            raise ValueError(f"physics background {self.background!r} (expected 'supports' or 'plane')")
        if self.coacd_preprocess not in ("auto", "on", "off"):
            raise ValueError(f"coacd_preprocess {self.coacd_preprocess!r} (expected 'auto', 'on' or 'off')")
        if not (self.mass > 0 and self.friction >= 0 and 0 <= self.restitution < 1):
            raise ValueError("physics: need mass > 0, friction ≥ 0 and 0 ≤ restitution < 1")
        if self.max_hull_vertices > self.drop_test.vertex_budget or self.max_hull_vertices < 4:
            raise ValueError("physics: need 4 ≤ max_hull_vertices ≤ drop_test.vertex_budget")
        if self.workers < 0:
            raise ValueError("physics: workers must be ≥ 0 (0: one per CPU core)")
        if self.max_parts > self.drop_test.part_buckets[-1]:
            raise ValueError("physics: max_parts exceeds the drop test's largest part bucket")
