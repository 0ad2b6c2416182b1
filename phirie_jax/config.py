"""Stage configs: frozen dataclasses whose defaults are the φ-RIE paper's numbers.

Where the paper gives a number it is the default and the field says so ("paper");
every other default is ours and the field says why. Lengths are metres, angles degrees.
Fields that fix array shapes (block sizes, frames per step) are static: each distinct
value is one compiled program.
"""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class SurfaceConfig:
    """The splat-derived scene surface: TSDF fusion of rendered depth, then a mesh.

    Attributes:
        voxel: TSDF voxel edge (paper: 5 mm).
        truncation: TSDF truncation distance (paper: about 2 cm).
        min_alpha: only pixels whose rendered alpha reaches this are fused (paper: 0.6).
        view_stride: fuse every k-th training view (1 = all of them).
        depth_max: rendered depth beyond this is ignored (far floor and background).
        backend: "jax" (``kernels.tsdf`` on a sparse block grid, then surface nets on the host)
            or "open3d" (Open3D's ``VoxelBlockGrid``, then marching cubes). Measured on 36 views
            of 320×240 (``experiments/results/``): Open3D 1.3 s fuse + 1.2 s mesh on the 2-core
            CPU; the JAX kernel 60–90 s on that CPU (it updates every allocated voxel for every
            frame) and 0.036 s on an H100, but its NumPy surface nets take ~30 s. So "open3d"
            is the default; both give the same surface to within a voxel.
        block: voxels per block edge of the JAX grid (static: one compiled program per value).
        frames_per_step: frames fused per step of the JAX scan (vmapped; static).
        min_weight: a voxel needs this many fused observations to take part in the mesh.
        snap_radius: ours, beyond the paper. Alpha-composited depth of overlapping splats is
            biased towards the camera (front disks win; measured 2–9 mm on the synthetic
            captures), so each mesh vertex is moved along its normal by the median offset of
            the ``snap_neighbours`` nearest opaque Gaussian centres within this radius (measured
            after: median 0.0 mm). 0 turns it off.
        snap_neighbours: Gaussian centres consulted per vertex.
        snap_min_opacity: only Gaussians at least this opaque are surface evidence.
    """

    voxel: float = 0.005
    truncation: float = 0.02
    min_alpha: float = 0.6
    view_stride: int = 1
    depth_max: float = 4.0
    backend: str = "open3d"
    block: int = 8
    frames_per_step: int = 4
    min_weight: float = 1.0
    snap_radius: float = 0.015
    snap_neighbours: int = 8
    snap_min_opacity: float = 0.5

    def __post_init__(self):
        if self.backend not in ("jax", "open3d"):
            raise ValueError(f"surface backend {self.backend!r} (expected 'jax' or 'open3d')")
        if not (self.voxel > 0 and self.truncation >= self.voxel and self.view_stride >= 1):
            raise ValueError("surface: need voxel > 0, truncation ≥ voxel and view_stride ≥ 1")


@dataclasses.dataclass(frozen=True)
class AutoMaskConfig:
    """Automatic instance discovery without learned weights (``--masks auto``).

    Supports are upward-facing planes of the observed surface; what stands on a support
    is clustered by Euclidean distance; each cluster is then projected into every view
    with occlusion (first hit on the surface) to give per-view masks.

    Attributes:
        sample_stride: pixel stride of the rays that sample the observed surface.
        sample_voxel: the observed surface samples are thinned to one per voxel of this size.
        up_max_tilt_deg: a support's normal is within this angle of "up" (the mean image-up
            direction of the cameras, refined by the largest support).
        plane_threshold: points this close to a support plane belong to it.
        min_support_area: a support covers at least this area (m²) of upward-facing surface.
        footprint_cell: grid cell of a support's 2D footprint (holes under objects are filled).
        cluster_eps: points closer than this are in the same cluster (the synthetic scenes keep
            objects ≥ 2 cm apart; touching objects merge, as in any geometric segmentation).
        min_cluster_points: smaller clusters are rejected (noise, floaters).
        max_object_extent: larger clusters are furniture or walls, not movable objects.
        max_object_height: points higher than this above their support are not considered.
        max_base_gap: a cluster stands on its support when its lowest point is this close.
        min_object_height: a cluster's top is at least this high above its support (a noisy
            splat-derived floor has bumps of up to 2.4 cm; flatter objects are missed).
        ransac_iterations: plane hypotheses for the dominant support (seeded, deterministic).
        seed: RANSAC seed.
    """

    sample_stride: int = 2
    sample_voxel: float = 0.005
    up_max_tilt_deg: float = 15.0
    plane_threshold: float = 0.01
    min_support_area: float = 0.05
    footprint_cell: float = 0.02
    cluster_eps: float = 0.015
    min_cluster_points: int = 40
    max_object_extent: float = 0.5
    max_object_height: float = 0.6
    max_base_gap: float = 0.03
    min_object_height: float = 0.03
    ransac_iterations: int = 256
    seed: int = 0


@dataclasses.dataclass(frozen=True)
class ObserveConfig:
    """Scene Observation: masks → first-hit lifting onto the surface → voxel association.

    Attributes:
        voxel: association voxel edge; each (view, mask) becomes a set of these (paper: 2 cm).
        overlap: two proposals of different views are linked when the IoU of their voxel
            sets reaches this (paper: 0.25). IoU rather than overlap-over-the-smaller-set, so
            the contact layer shared by two touching objects does not chain them.
        min_views: an instance needs this many supporting views (paper: ≥ 2).
        pixel_stride: mask pixels are lifted on this stride (every k-th row and column).
        mask_erosion_px: mask pixels this close to another label are not lifted (a ray through
            a silhouette edge may hit what is behind the object). 0 lifts every pixel.
        min_proposal_points: a (view, mask) needs this many lifted points, else it is recorded
            as rejected ("too small").
        points_voxel: an instance's observed points Q_i are thinned to one per voxel of this
            size (the surface resolution).
        max_points: at most this many points in Q_i (a seeded subsample beyond it).
        surface_source: "auto" (the scan mesh when the scene has one, else splat-derived),
            "mesh" (require the scan mesh) or "splats" (always build it from the Gaussians).
        surface: splat-derived surface settings.
        auto: automatic mask settings.
    """

    voxel: float = 0.02
    overlap: float = 0.25
    min_views: int = 2
    pixel_stride: int = 2
    mask_erosion_px: int = 1
    min_proposal_points: int = 3
    points_voxel: float = 0.005
    max_points: int = 50_000
    surface_source: str = "auto"
    surface: SurfaceConfig = SurfaceConfig()
    auto: AutoMaskConfig = AutoMaskConfig()

    def __post_init__(self):
        if self.surface_source not in ("auto", "mesh", "splats"):
            raise ValueError(f"surface_source {self.surface_source!r} (expected 'auto', 'mesh' or 'splats')")
        if not (0 < self.overlap <= 1):
            raise ValueError(f"overlap {self.overlap} (expected in (0, 1])")
        if self.min_views < 1 or self.pixel_stride < 1 or self.mask_erosion_px < 0:
            raise ValueError("need min_views ≥ 1, pixel_stride ≥ 1 and mask_erosion_px ≥ 0")


def to_dict(config) -> dict:
    """A config as plain JSON-ready values (nested configs included)."""
    return dataclasses.asdict(config)


@dataclasses.dataclass(frozen=True)
class RegistrationConfig:
    """Batched Sim(3) registration of a candidate shape to an instance's observed points Q_i.

    Attributes:
        points: points sampled on the candidate mesh, P (paper: 20K). Every candidate has
            exactly this many, so it is one static shape.
        num_yaws: yaws per up axis (paper: 36, i.e. 10° steps).
        tau: clip distance of E_i(S) and of the observation-support check (paper: 3 cm).
        scale_multipliers: ours — multipliers of the robust-extent scale init tried in the sweep.
        top_k: ours — best sweep hypotheses per refined up axis (ICP, then scale).
        refine_other_axes: ours — besides the candidate's own up (+z), the refinement runs on the
            axes with the lowest sweep score, this many of them. On the development scene the
            true axis had the lowest sweep score of all six in 24/24 random frames; 2 keeps a
            margin and halves the refinement work of refining all six (5).
        sweep_model_points / sweep_obs_points: ours — the sweep scores every hypothesis on these
            many leading (random) points of P and Q; refined hypotheses are rescored on all of
            them. Measured in ``experiments/bench_register.py``.
        icp_model_points / icp_obs_points: ours — points matched in ICP and scale refinement.
        score_obs_points: ours — at most this many points of Q in the final scores (a random
            subset; the mean of clipped distances moves by well under 0.1 mm beyond it).
        icp_iterations / scale_iterations: ours — fixed iteration counts.
        icp_max_correspondence: ours — ICP ignores matches farther than this (2τ).
        rotation: ours — "full" (3D Kabsch) or "yaw" (rotation about up only) in ICP.
        chunk: queries per brute-force nearest-neighbour block (static).
        hypothesis_batch: hypotheses vmapped together (static; memory ∝ batch · chunk · points).
            None: 36 on a CPU, all of them on a GPU (measured: the whole search takes 7 ms on an
            H100 with all 648 together).
        min_obs_bucket: Q is padded to the next power of two, at least this (static buckets).
        batched_retry: ours — True scores all six up axes in the first (and only) kernel call, so
            the retry is a host-side choice; False searches +z first and calls the kernel again
            with the other five axes only for candidates whose checks fail. Measured
            (``experiments/bench_register.py``): on an H100 the six-axis call takes as long as the
            +z one (7 ms), so the retry is free; on the 2-core CPU it costs 3.1× the +z call
            (lazy: 1× when +z passes, 3.4× when it does not).
        seed: sampling seed (P on the mesh, subsets of Q).
    """

    points: int = 20_000
    num_yaws: int = 36
    tau: float = 0.03
    scale_multipliers: tuple[float, ...] = (0.85, 1.0, 1.15)
    top_k: int = 1
    refine_other_axes: int = 2
    sweep_model_points: int = 512
    sweep_obs_points: int = 512
    icp_model_points: int = 2048
    icp_obs_points: int = 2048
    score_obs_points: int = 4096
    icp_iterations: int = 20
    scale_iterations: int = 10
    icp_max_correspondence: float = 0.06
    rotation: str = "full"
    chunk: int = 256
    hypothesis_batch: int | None = None
    min_obs_bucket: int = 256
    batched_retry: bool = True
    seed: int = 0

    def __post_init__(self):
        if self.rotation not in ("full", "yaw"):
            raise ValueError(f"registration rotation {self.rotation!r} (expected 'full' or 'yaw')")
        if min(self.sweep_model_points, self.icp_model_points) > self.points:
            raise ValueError("registration: sweep/ICP subsets cannot exceed the sampled points")
        if self.num_yaws < 1 or self.top_k < 1 or not self.scale_multipliers:
            raise ValueError("registration: need num_yaws ≥ 1, top_k ≥ 1 and a scale multiplier")


@dataclasses.dataclass(frozen=True)
class ObjectsConfig:
    """Object construction: candidates → registration → checks → selection → assets.

    Attributes:
        generators: the candidate pool in priority order (the order is the fixed-priority
            baseline and the last tie-break): "external" (every mesh in candidates/<id>/, by
            name), "external:<name>" (one of them), "visual_hull", "primitive", "extrude".
        selection: "evidence" (rank every candidate lexicographically on its checks, the paper's
            default) or "priority" (the first candidate, in pool order, whose checks all pass;
            else the first numerically valid one).
        retry: the bounded retry — a candidate whose checks fail with its own up (+z) is tried
            with the 5 other signed up axes (paper).
        strict: reject an object whose chosen candidate has a failed check (``--strict``); by
            default it is kept and the failed checks are recorded.
        min_points: an instance with fewer observed points fails ("too few points").
        max_residual: registration check, E_i(S) in metres (ours, from the development seeds:
            ground-truth shapes score 4–7 mm, wrong up axes and wrong shapes ≥ 10 mm).
        max_scale_discrepancy: scale check, |ln(s / s_init)| between the registered scale and the
            robust-extent init of its axis (ours).
        min_support: observation support check: fraction of Q within τ of the asset (ours).
        min_hull_volume: collision check (convex-hull stand-in until the physics stage's convex
            decomposition): the hull must be a valid solid of at least this volume, m³.
        settle_threshold: settling check: drift from the drop test (paper: 3 cm). Filled in by
            the physics stage; until then recorded as not run.
        snap_to_support: ours — after registration, move the asset vertically so its lowest point
            is on the support plane when it is within τ of it.
        hull_resolution: voxels along each side of the visual hull's carving grid (static shape);
            the voxel edge is the carving box's longest side over this.
        hull_margin: the carving box is Q's robust box grown on each side by this plus a fifth of
            its horizontal extent (room for the parts the observation missed).
        hull_dilate_px: the instance's mask is dilated by this many pixels before carving. 0: the
            synthetic scenes' rendered masks measured 1–2 px wider than the projected mesh already
            (each extra pixel grew the hull's volume by a further 15–25 %).
        hull_max_misses: a voxel survives this many views that see background where it projects.
        extrude_cell: footprint/heightfield cell of the extruded generator.
        mesh_smooth: Gaussian smoothing (in voxels) of an occupancy grid before meshing.
        gaussian_radius: captured Gaussians within this of Q_i and of the placed mesh belong
            to the object's appearance.
        base_clearance: captured Gaussians lower than this above the support are the support's.
        fill_spacing: spacing of new Gaussians on mesh regions the capture never saw.
        fill_min_distance: mesh points farther than this from every kept Gaussian are unseen.
        colour_neighbours: new Gaussians take the mean colour of this many nearest kept ones.
        registration: the registration kernel's settings.
    """

    generators: tuple[str, ...] = ("external", "visual_hull", "extrude", "primitive")
    selection: str = "evidence"
    retry: bool = True
    strict: bool = False
    min_points: int = 50
    max_residual: float = 0.010
    max_scale_discrepancy: float = 0.15
    min_support: float = 0.9
    min_hull_volume: float = 1e-7
    settle_threshold: float = 0.03
    snap_to_support: bool = True
    hull_resolution: int = 64
    hull_margin: float = 0.03
    hull_dilate_px: int = 0
    hull_max_misses: int = 0
    extrude_cell: float = 0.004
    mesh_smooth: float = 0.8
    gaussian_radius: float = 0.01
    base_clearance: float = 0.003
    fill_spacing: float = 0.004
    fill_min_distance: float = 0.008
    colour_neighbours: int = 8
    registration: RegistrationConfig = RegistrationConfig()

    def __post_init__(self):
        if self.selection not in ("evidence", "priority"):
            raise ValueError(f"objects selection {self.selection!r} (expected 'evidence' or 'priority')")
        known = ("external", "visual_hull", "primitive", "extrude")
        for g in self.generators:
            if g not in known and not g.startswith("external:"):
                raise ValueError(f"objects generator {g!r} (expected one of {known} or 'external:<name>')")
        if not self.generators:
            raise ValueError("objects: the candidate pool (generators) is empty")


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


@dataclasses.dataclass(frozen=True)
class BackgroundConfig:
    """Background branch: coupled source-Gaussian removal, inpainting targets, plane-disk fill.

    Removal, R_i = R_obs ∪ R_asset ∪ R_mask (``construct.removal``):
        obs_radius: Gaussians within this of the observed surface Q_i (paper: 3 cm).
        asset_radius: ... within this of the registered asset's surface (paper: 2.4 cm).
        mask_votes: centres inside the expanded bounds projecting inside the instance mask, visible,
            in at least this many views (paper: 2).
        bounds_margin: ours — the expanded bounds are the box of Q_i and the placed asset grown by this.
        mask_views: ours — the instance's largest masks consulted (each is one crop render).
        occlusion_tolerance: ours — a centre more than this behind the depth rendered at its pixel is
            occluded in that view and does not vote (the paper's code has no occlusion test).
        remove_statuses: objects with these statuses are removed; the others stay in the background.
    Targets (``construct.inpaint``):
        inpaint: "telea" (OpenCV's Telea, the default) or "ns" (Navier–Stokes).
        inpaint_radius: OpenCV's inpainting neighbourhood, pixels.
        region_weight: a pixel is in an edit's region where the removed Gaussians' composited weight
            reaches this (their rendered alpha in the capture).
        region_dilate_px: the region is grown by this many pixels.
        loss_ring_px: the fit also covers this many pixels around the region, where the target is the
            kept scene itself (the new disks must not change what was already right).
        explained_alpha: inside the region, a pixel the kept Gaussians cover at least this opaquely, at or
            in front of the support plane (``plane_depth_tolerance``), is kept as rendered, not inpainted.
        plane_depth_tolerance: metres.
        crop_sizes / mask_crop_sizes: static square crop sizes of the target and R_mask passes (pixels).
        crop_margin_px: pixels around a region in its crop.
        targets: ours — a folder of externally edited targets replacing ours (format in
            ``construct.inpaint``); None: OpenCV.
        write_targets: write the targets (and masks) under ``background/targets/`` for inspection or editing.
    Support plane (``construct.fill``):
        ring_inner / ring_outer: the plane is fitted to kept Gaussian centres this far from the object's
            footprint (ours: 1–8 cm) ...
        ring_height: ... and within this of the object's base height.
        plane_threshold: RANSAC inlier distance (ours: 5 mm).
        ransac_iterations / seed: hypotheses (seeded, deterministic).
        max_tilt_deg: a support plane's normal is within this of up.
        plane_base_tolerance: ours — ... and the plane passes this close to the object's base (the
            construction stage's support height; a table's underside has as many ring points).
        min_plane_points / min_inlier_fraction: fewer ring points or inliers: an unsupported region.
        min_opacity: only Gaussians at least this opaque are surface evidence.
    Fill (``construct.fill``, ``kernels.fill``):
        grid: disk grid spacing on the plane (paper: 5 mm).
        margin: ours — the fill covers the exposed footprint grown by this (overlaps the kept surface).
        cover_factor: ours — a grid cell is covered by the kept surface when a kept plane Gaussian lies
            within this many times the kept Gaussians' median spacing.
        slab: kept Gaussians within this of the plane are surface (coverage) and are rendered with the
            disks in the refinement; the others are fixed front/back layers.
        disk_sigma / disk_thickness: in-plane σ of a new disk as a fraction of ``grid``; normal σ as a
            fraction of the in-plane σ (the synthetic capture's own disk shape).
        max_disk_sigma: the fit keeps a disk's in-plane σ within [¼, this] × ``grid`` (it bounds the
            pixels a disk can reach, hence the kept Gaussians each step renders).
        init_opacity: of a new disk.
        colour_neighbours: disks no target sees take the mean colour of this many nearest kept plane
            Gaussians ("neighbouring observations").
        max_disks: per object; more is a failed completion (an implausibly large exposed region).
    Refinement (``kernels.fill``):
        iterations: Adam steps on the new disks only.
        dssim_weight: λ of (1 − λ) L1 + λ D-SSIM (3DGS: 0.2).
        lr_colour / lr_opacity / lr_offset / lr_scale: learning rates of the SH DC, opacity logit,
            in-plane offset (tanh-bounded by one grid cell) and in-plane log-scale.
    """

    obs_radius: float = 0.03
    asset_radius: float = 0.024
    mask_votes: int = 2
    bounds_margin: float = 0.02
    mask_views: int = 8
    occlusion_tolerance: float = 0.01
    remove_statuses: tuple[str, ...] = ("accepted",)
    inpaint: str = "telea"
    inpaint_radius: int = 5
    region_weight: float = 0.02
    region_dilate_px: int = 2
    loss_ring_px: int = 4
    explained_alpha: float = 0.95
    plane_depth_tolerance: float = 0.01
    crop_sizes: tuple[int, ...] = (64, 128)
    mask_crop_sizes: tuple[int, ...] = (64, 128)
    crop_margin_px: int = 8
    targets: str | None = None
    write_targets: bool = True
    ring_inner: float = 0.01
    ring_outer: float = 0.08
    ring_height: float = 0.025
    plane_threshold: float = 0.005
    ransac_iterations: int = 256
    seed: int = 0
    max_tilt_deg: float = 45.0
    plane_base_tolerance: float = 0.015
    min_plane_points: int = 30
    min_inlier_fraction: float = 0.3
    min_opacity: float = 0.5
    grid: float = 0.005
    margin: float = 0.01
    cover_factor: float = 1.0
    slab: float = 0.01
    disk_sigma: float = 0.9
    disk_thickness: float = 0.12
    max_disk_sigma: float = 1.25
    init_opacity: float = 0.9
    colour_neighbours: int = 8
    max_disks: int = 40_000
    iterations: int = 40
    dssim_weight: float = 0.2
    lr_colour: float = 0.05
    lr_opacity: float = 0.05
    lr_offset: float = 0.05
    lr_scale: float = 0.02

    def __post_init__(self):
        if self.inpaint not in ("telea", "ns"):
            raise ValueError(f"background inpaint {self.inpaint!r} (expected 'telea' or 'ns')")
        if not (self.obs_radius >= 0 and self.asset_radius >= 0 and self.mask_votes >= 1):
            raise ValueError("background: need obs_radius ≥ 0, asset_radius ≥ 0 and mask_votes ≥ 1")
        if not (self.grid > 0 and self.margin >= 0 and 0 < self.init_opacity < 1):
            raise ValueError("background: need grid > 0, margin ≥ 0 and 0 < init_opacity < 1")
        if not self.crop_sizes or not self.mask_crop_sizes or min(self.crop_sizes + self.mask_crop_sizes) < 16:
            raise ValueError("background: crop sizes must be given and at least one tile (16 px)")
        if self.iterations < 0 or not (0 <= self.dssim_weight <= 1):
            raise ValueError("background: need iterations ≥ 0 and 0 ≤ dssim_weight ≤ 1")
