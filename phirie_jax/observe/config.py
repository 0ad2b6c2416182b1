"""Scene Observation's config: frozen dataclasses whose defaults are the φ-RIE paper's numbers.

Where the paper gives a number it is the default and the field says so ("paper");
every other default is ours and the field says why. Lengths are metres, angles degrees.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

from phirie_jax.observe.prompt_config import PromptConfig
from phirie_jax.ranges import (
    ANGLE_DEG,
    AT_LEAST_ONE,
    FRACTION,
    NON_NEGATIVE,
    POSITIVE,
    POSITIVE_FRACTION,
    Choice,
    Range,
    at_least,
    check_ranges,
)

SurfaceBackend = Literal["jax", "open3d"]
SurfaceSource = Literal["auto", "mesh", "splats"]


@dataclasses.dataclass(frozen=True)
class FloaterConfig:
    """Gaussians left out of the splat-derived surface (``observe/floaters.py``); ours, beyond
    the paper. Every rule is relative to the scene's own Gaussians, so it holds in any units.

    Attributes:
        enabled: False keeps every Gaussian.
        min_opacity: more transparent Gaussians are haze (3DGS training itself prunes below
            0.005; at 0.05 a Gaussian needs ~14 layers to reach the fused alpha of 0.6).
        large_mads: a Gaussian whose largest axis (log) is more than this many robust
            deviations above the scene's median is a background or sky blob.
        neighbours: the isolation rule looks at the distance to this many-th nearest centre.
        isolated_factor: a centre whose ``neighbours``-th neighbour is farther than this times
            the scene's median such distance floats in free space.
    """

    enabled: bool = True
    min_opacity: float = 0.05
    large_mads: float = 5.0
    neighbours: int = 8
    isolated_factor: float = 10.0

    def __post_init__(self):
        check_ranges(self, {"min_opacity": Range(0, 1, high_open=True), "large_mads": POSITIVE,
                            "neighbours": AT_LEAST_ONE, "isolated_factor": Range(1, low_open=True)})


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
        memory_budget_gb: the TSDF grid is sized from the blocks the depth samples reach; when
            those blocks would take more than this (GB, an estimate per backend) the surface is
            refused before anything is allocated, with the bounds, voxel and block count. At
            5 mm voxels a metre² of surface needs ~1,600 blocks of 8³ (measured); 4 GB then holds
            ~150–300 m² with Open3D (4 KB a block) and ~20–30 m² with the JAX kernel (~80 KB a
            block with its per-frame intermediates), the range from power-of-two padding.
        floaters: Gaussians left out of the depth rendering and the snapping.
    """

    voxel: float = 0.005
    truncation: float = 0.02
    min_alpha: float = 0.6
    view_stride: int = 1
    depth_max: float = 4.0
    backend: SurfaceBackend = "open3d"
    block: int = 8
    frames_per_step: int = 4
    min_weight: float = 1.0
    snap_radius: float = 0.015
    snap_neighbours: int = 8
    snap_min_opacity: float = 0.5
    memory_budget_gb: float = 4.0
    floaters: FloaterConfig = FloaterConfig()

    def __post_init__(self):
        check_ranges(self, {
            "backend": Choice.of(SurfaceBackend), "voxel": POSITIVE, "truncation": at_least(self.voxel, "voxel"), "min_alpha": POSITIVE_FRACTION,
            "view_stride": AT_LEAST_ONE, "depth_max": POSITIVE, "block": AT_LEAST_ONE, "frames_per_step": AT_LEAST_ONE,
            "min_weight": POSITIVE, "snap_radius": NON_NEGATIVE, "snap_neighbours": AT_LEAST_ONE,
            "snap_min_opacity": FRACTION, "memory_budget_gb": POSITIVE})


@dataclasses.dataclass(frozen=True)
class AutoMaskConfig:
    """Automatic instance discovery without learned weights (``--masks auto``).

    Supports are planes of the observed surface's sample positions near the scene's up (seeded
    by the frame's support plane, ``observe/support_fit.py``), each with its relief; what stands
    on a support is clustered by Euclidean distance; a cluster becomes an instance only when it is
    tall enough and seen by enough of the views that look at it; each is then projected into every
    view with occlusion (first hit on the surface) to give per-view masks.

    Attributes:
        sample_stride: pixel stride of the rays that sample the observed surface.
        sample_voxel: the observed surface samples are thinned to one per voxel of this size.
        up_max_tilt_deg: a support's normal is within this angle of up (the scene frame's +z).
        plane_threshold: points this close to a support surface belong to it (and RANSAC's
            inlier distance for the support planes).
        min_support_area: a support plane holds at least this area (m²) of surface samples
            within ``plane_threshold``.
        support_relief: ours — a support need not be flat (a duvet, a cloth): samples up to this
            far from its plane measure its relief (``relief_cell``), and heights are measured
            from that surface. 0: flat supports only.
        relief_cell: the relief is measured on cells of this edge (the densest layer of each
            cell's samples, so an object covering less of a cell than the support does not raise
            it) and interpolated between them: folds wider than about two cells are support.
        footprint_cell: grid cell of a support's 2D footprint (holes under objects are filled).
        cluster_eps: points closer than this are in the same cluster (the synthetic scenes keep
            objects ≥ 2 cm apart; touching objects merge, as in any geometric segmentation).
        min_cluster_points: smaller clusters are rejected (noise, floaters).
        max_object_extent: larger clusters are furniture or walls, not movable objects.
        max_object_height: points higher than this above their support are not considered.
        max_base_gap: a cluster stands on its support when its lowest point is this close.
        min_object_height: a cluster's top is at least this high above its support (a noisy
            splat-derived floor has bumps of up to 2.4 cm; flatter objects are missed).
        min_views: a cluster is an object only when at least this many views see it (each with
            ``min_view_pixels`` sampled pixels on it). Paper: an instance needs ≥ 2 supporting
            views; ours raises it to 3 for what no mask backs (the optimiser's floaters and floor
            bumps show in a few views only).
        min_view_fraction: ... and at least this fraction of the views that look at it (its
            centre in the image, in front of the camera, not hidden by the surface). Ours: a
            real object is seen from most views that face it; the floor bumps gsplat's
            densification leaves were seen in 4–8 of 36 (0.11–0.22). Both rules hold again for
            each instance after association (its supporting views, and its ``confidence``: those
            views over the views that have its centre in the image).
        min_view_pixels: sampled pixels (on ``sample_stride``) a view needs on a cluster to see it.
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
    support_relief: float = 0.04
    relief_cell: float = 0.08
    min_views: int = 3
    min_view_fraction: float = 0.5
    min_view_pixels: int = 4

    def __post_init__(self):
        check_ranges(self, {
            "sample_stride": AT_LEAST_ONE, "sample_voxel": POSITIVE, "up_max_tilt_deg": ANGLE_DEG,
            "plane_threshold": POSITIVE, "min_support_area": POSITIVE, "footprint_cell": POSITIVE,
            "cluster_eps": POSITIVE, "min_cluster_points": AT_LEAST_ONE, "max_object_extent": POSITIVE,
            "max_object_height": POSITIVE, "max_base_gap": NON_NEGATIVE, "min_object_height": NON_NEGATIVE,
            "support_relief": NON_NEGATIVE, "relief_cell": POSITIVE, "min_views": AT_LEAST_ONE, "min_view_fraction": FRACTION,
            "min_view_pixels": AT_LEAST_ONE})


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
        silhouette_agreement: a point of Q_i stays when at least this fraction of the instance's
            views that show it on the instance's label or on none (0) show it on the
            instance's label. Every point of an object lies inside its silhouette in every
            view; a pixel lifted past a mask's edge lands on what is behind the object (the
            table, a wall) and falls outside the silhouette in most other views. A view that
            shows another instance there abstains (it may hide the point). 0 keeps every point.
        support_clearance: points of Q_i less than this above the support the instance stands on
            (``observe.support``: a plane found on the scene surface, ``Support.is_plane``) are the
            support's: a mask that bleeds past the object's base lifts a ring of table that
            every view agrees with. None keeps them.
        working_width: observation renders and ray casts at this image width whatever the
            photos' size (a wider photo's camera is scaled down; the height follows): the
            depth rendered for the splat-derived surface, the rays that lift mask pixels and
            the rays that make automatic masks. Masks and outputs stay at the photos' size.
            0 = the photos' size. 640 bounds the per-pixel work of a 4K phone capture to what
            a 640-wide one costs; photos at most this wide are observed as they are.
        surface_source: "auto" (the scan mesh when the scene has one, else splat-derived),
            "mesh" (require the scan mesh) or "splats" (always build it from the Gaussians).
        surface: splat-derived surface settings.
        auto: automatic mask settings.
        prompts: how prompts (a box or a click in a photo) become objects.
    """

    voxel: float = 0.02
    overlap: float = 0.25
    min_views: int = 2
    pixel_stride: int = 2
    mask_erosion_px: int = 1
    min_proposal_points: int = 3
    points_voxel: float = 0.005
    max_points: int = 50_000
    silhouette_agreement: float = 0.75
    support_clearance: float | None = 0.005
    working_width: int = 640
    surface_source: SurfaceSource = "auto"
    surface: SurfaceConfig = SurfaceConfig()
    auto: AutoMaskConfig = AutoMaskConfig()
    prompts: PromptConfig = PromptConfig()

    def __post_init__(self):
        check_ranges(self, {
            "surface_source": Choice.of(SurfaceSource), "voxel": POSITIVE, "overlap": POSITIVE_FRACTION, "min_views": AT_LEAST_ONE, "pixel_stride": AT_LEAST_ONE,
            "mask_erosion_px": NON_NEGATIVE, "min_proposal_points": AT_LEAST_ONE, "points_voxel": POSITIVE,
            "max_points": AT_LEAST_ONE, "silhouette_agreement": FRACTION, "support_clearance": NON_NEGATIVE,
            "working_width": Range(0, bound="0 = the photos' size")})
