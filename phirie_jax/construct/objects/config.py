"""Object construction's config: frozen dataclasses whose defaults are the φ-RIE paper's numbers.

Where the paper gives a number it is the default and the field says so ("paper");
every other default is ours and the field says why. Lengths are metres, angles degrees.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

from kernels.registration import Rotation, SearchSpec
from phirie_jax.ranges import (
    AT_LEAST_ONE,
    FRACTION,
    NON_NEGATIVE,
    POSITIVE,
    Choice,
    Each,
    Range,
    at_most,
    check_ranges,
)

Selection = Literal["evidence", "priority"]

# The search fields the object stage sets for each call: which axes (own up first, or all six for a
# batched retry), how many hypotheses go through one vmap, and whether to snap to the support.
PER_CALL_SEARCH_FIELDS = ("axes", "hypothesis_batch", "snap_to_support")


@dataclasses.dataclass(frozen=True)
class RegistrationConfig:
    """Batched Sim(3) registration of a candidate shape to an instance's observed points Q_i.

    Attributes:
        search: the kernel's static search (``kernels.registration.SearchSpec``): P's size
            (``model_points``, paper: 20K), yaws per up axis (paper: 36, i.e. 10° steps), and ours —
            scale multipliers, the refined axes and hypotheses, the point subsets of the sweep, ICP
            and scores, iteration counts, ``rotation`` ("full" or "yaw") and the nearest-neighbour
            ``chunk``. Its ``axes``, ``hypothesis_batch`` and ``snap_to_support`` are set for each
            search by the object stage (``retry``, ``batched_retry``, ``snap_to_support``, and
            ``hypothesis_batch`` here) and must stay at their defaults. On the development scene
            the true axis had the lowest sweep score of all six in 24/24 random frames, so
            ``refine_other_axes`` 2 keeps a margin at less than half the work of refining all
            five; subset sizes are measured in ``experiments/bench_register.py``.
        tau: clip distance of E_i(S) and of the observation-support check (paper: 3 cm).
        icp_max_correspondence: ours — ICP ignores matches farther than this (2τ).
        hypothesis_batch: hypotheses vmapped together (static; memory ∝ batch · chunk · points).
            None: 36 on a CPU, all of them on a GPU (the whole search in one call there:
            docs/performance.md, "Registration").
        min_obs_bucket: Q is padded to the next power of two, at least this (static buckets).
        batched_retry: ours — True scores all six up axes in the first (and only) kernel call, so
            the retry is a host-side choice; False searches +z first and calls the kernel again
            with the other five axes only for candidates whose checks fail. On a GPU the six-axis
            call takes as long as the +z one, so the retry is free; on a CPU the lazy order saves
            time when +z passes (docs/performance.md, "Registration").
        seed: sampling seed (P on the mesh, subsets of Q).
        skip_cut_base: ours — E leaves out the placed candidate's points below the cut the
            observation made above the plane support the instance stands on (recorded with the
            instance's support, ``ObserveConfig.support_clearance``): the observation keeps no
            point of Q there, so they have nothing to match (``kernels.registration.scored_model``).
            Measured on the gsplat-fitted scenes: the flat base of a bowl's extruded candidate,
            29 % of its area, was 0.52 cm of its 1.15 cm E. False scores every point (the paper's E).
    """

    search: SearchSpec = SearchSpec()
    tau: float = 0.03
    icp_max_correspondence: float = 0.06
    hypothesis_batch: int | None = None
    min_obs_bucket: int = 256
    batched_retry: bool = True
    seed: int = 0
    skip_cut_base: bool = True

    def __post_init__(self):
        s = self.search
        subset = at_most(s.model_points, "search.model_points", low=1)
        check_ranges(self, {
            "tau": POSITIVE, "icp_max_correspondence": POSITIVE, "hypothesis_batch": AT_LEAST_ONE,
            "min_obs_bucket": AT_LEAST_ONE, "seed": NON_NEGATIVE,
            "search.rotation": Choice.of(Rotation),
            "search.num_yaws": AT_LEAST_ONE, "search.scale_multipliers": Each(POSITIVE),
            "search.top_k": at_most(s.num_yaws * len(s.scale_multipliers), "search.num_yaws × scale multipliers", 1),
            "search.refine_other_axes": Range(0, 5), "search.model_points": AT_LEAST_ONE,
            "search.sweep_model_points": subset, "search.icp_model_points": subset,
            "search.sweep_obs_points": AT_LEAST_ONE, "search.icp_obs_points": AT_LEAST_ONE,
            "search.score_obs_points": AT_LEAST_ONE, "search.icp_iterations": NON_NEGATIVE,
            "search.scale_iterations": NON_NEGATIVE, "search.chunk": AT_LEAST_ONE})
        for name in PER_CALL_SEARCH_FIELDS:
            if getattr(s, name) != getattr(SearchSpec(), name):
                raise ValueError(f"registration.search.{name} is set for each search by the object stage "
                                 "(use retry, batched_retry, snap_to_support or registration.hypothesis_batch)")

    @property
    def points(self) -> int:
        """Points sampled on each candidate mesh (P): one static shape for every candidate."""
        return self.search.model_points


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
        max_relative_residual: ... or this fraction of the observed object's size (the diagonal of
            Q's 2–98 % box), when larger (ours). The development objects are 9–27 cm across, where
            1 cm holds; a shape carved on a ``hull_resolution`` grid over a larger object's box is
            already ~1/45 of its size off by its voxels alone, and a scale from a prior leaves
            metres uncertain by its factor. Real captures (45–50 cm across, free-space carved):
            E 3.0–3.6 % of the size, like gsplat-fitted synthetic objects (2–7 %); what gsplat's
            densification leaves on a table 5.5–29 % (``discovery_eval_gsplat``). Not for what
            automatic discovery found: a duvet's folds fit an extrusion within 3.2–4.1 % of their
            size (snowmiku), so discovery keeps ``max_residual`` alone.
        max_scale_discrepancy: scale check, |ln(s / s_init)| between the registered scale and the
            robust-extent init of its axis (ours).
        min_support: observation support check: fraction of Q within τ of the asset (ours).
        min_hull_volume: collision check (convex-hull stand-in until the physics stage's convex
            decomposition): the hull must be a valid solid of at least this volume, m³.
        settle_threshold: settling check: drift from the drop test (paper: 3 cm). Filled in by
            the physics stage; until then recorded as not run.
        mount_gap: ours — an object whose lowest observed point is more than ``settle_threshold``
            above the support under it, and whose Gaussians come within this of a wall behind it
            (``observe.support.Wall``, found behind a prompt's object), is mounted on that wall:
            its body is welded there (the physics stage's hold test replaces the drop test), and
            its mount check asks the placed asset to reach within this of the wall. A taxidermy fox
            head's Gaussians come 2.0 cm from its wall (the fox capture).
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
        hull_free_space_margin: a view saw through a voxel when its ray meets the observed surface
            more than this beyond the voxel's centre (``generators.free_space``).
        hull_free_space_views: ... and a voxel that this many views saw through is carved (0: the
            masks alone carve).
        extrude_cell: footprint/heightfield cell of the extruded generator.
        mesh_smooth: Gaussian smoothing (in voxels) of an occupancy grid before meshing.
        gaussian_radius: captured Gaussians within this of Q_i and of the placed mesh belong
            to the object's appearance; the background stage removes those within
            ``RemovalConfig.obs_radius`` of Q_i (paper: 3 cm), so this is that radius: what the
            background gives up for the object, the object carries (at 1 cm a plush's outer fur
            and whatever touched it vanished from the converted scene).
        gaussian_mesh_radius: ... and within this of the placed mesh (or inside it). Tighter keeps
            the halo beyond the shape (a wall behind a mounted head) out of the object's silhouette
            but loses it from the scene (real_eval, held-out ΔPSNR / silhouette IoU: 3 cm fox −0.14 dB
            / 0.78, snowmiku −0.27 / 0.84; 2 cm −0.18 / 0.82 and −0.59 / 0.88; 1 cm −0.26 / 0.85
            and −0.55 / 0.91): the default keeps the scene.
        base_clearance: captured Gaussians lower than this above the support are the support's.
        fill_spacing: spacing of new Gaussians on mesh regions the capture never saw.
        fill_min_distance: mesh points farther than this from every kept Gaussian are unseen.
        colour_neighbours: new Gaussians take the mean colour of this many nearest kept ones.
        workers: objects constructed at once, in threads (ours; 0: one per CPU core, at most one
            per object; 1: one after another). The results do not depend on it.
        registration: the registration kernel's settings.
    """

    generators: tuple[str, ...] = ("external", "visual_hull", "extrude", "primitive")
    selection: Selection = "evidence"
    retry: bool = True
    strict: bool = False
    min_points: int = 50
    max_residual: float = 0.010
    max_relative_residual: float = 0.04
    max_scale_discrepancy: float = 0.15
    min_support: float = 0.9
    min_hull_volume: float = 1e-7
    settle_threshold: float = 0.03
    mount_gap: float = 0.03
    snap_to_support: bool = True
    hull_resolution: int = 64
    hull_margin: float = 0.03
    hull_dilate_px: int = 0
    hull_max_misses: int = 0
    hull_free_space_margin: float = 0.005
    hull_free_space_views: int = 2
    extrude_cell: float = 0.004
    mesh_smooth: float = 0.8
    gaussian_radius: float = 0.03
    gaussian_mesh_radius: float = 0.03
    base_clearance: float = 0.003
    fill_spacing: float = 0.004
    fill_min_distance: float = 0.008
    colour_neighbours: int = 8
    workers: int = 0
    registration: RegistrationConfig = RegistrationConfig()

    def __post_init__(self):
        known = ("external", "visual_hull", "primitive", "extrude")
        for g in self.generators:
            if g not in known and not g.startswith("external:"):
                raise ValueError(f"objects generator {g!r} (expected one of {known} or 'external:<name>')")
        if not self.generators:
            raise ValueError("objects: the candidate pool (generators) is empty")
        check_ranges(self, {
            "selection": Choice.of(Selection), "min_points": AT_LEAST_ONE, "max_residual": POSITIVE,
            "max_relative_residual": NON_NEGATIVE, "max_scale_discrepancy": POSITIVE,
            "min_support": FRACTION, "min_hull_volume": NON_NEGATIVE, "settle_threshold": POSITIVE,
            "mount_gap": POSITIVE,
            "hull_resolution": Range(2), "hull_margin": NON_NEGATIVE, "hull_dilate_px": NON_NEGATIVE,
            "hull_max_misses": NON_NEGATIVE, "hull_free_space_margin": NON_NEGATIVE,
            "hull_free_space_views": NON_NEGATIVE, "extrude_cell": POSITIVE, "mesh_smooth": NON_NEGATIVE,
            "gaussian_radius": NON_NEGATIVE, "gaussian_mesh_radius": NON_NEGATIVE, "base_clearance": NON_NEGATIVE, "fill_spacing": POSITIVE,
            "fill_min_distance": NON_NEGATIVE, "colour_neighbours": AT_LEAST_ONE,
            "workers": Range(0, bound="0: one per CPU core")})
