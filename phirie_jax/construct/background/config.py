"""The background stage's config, one frozen dataclass per step, whose defaults are the φ-RIE paper's numbers.

Where the paper gives a number it is the default and the field says so ("paper");
every other default is ours and the field says why (the longer notes behind some of them:
``experiments/results/background_notes.md``). Lengths are metres, angles degrees.

    BackgroundConfig
      removal   RemovalConfig   R_i = R_obs ∪ R_asset ∪ R_mask          (``removal``)
      crops     CropConfig      static crop sizes of the render passes  (``views``)
      plane     PlaneConfig     the robust support plane                (``plane``)
      fill      FillConfig      the disk lattice on the exposed cells   (``plane``, ``kernels.fill``)
      targets   TargetsConfig   inpainting targets                      (``targets``)
      refine    RefineConfig    the Adam fit of the disks               (``refine``, ``kernels.fill``)
      seed      RANSAC hypotheses and the asset's surface samples
"""

from __future__ import annotations

import dataclasses
from typing import Literal

from phirie_jax.ranges import (
    ANGLE_DEG,
    AT_LEAST_ONE,
    FRACTION,
    NON_NEGATIVE,
    OPEN_FRACTION,
    POSITIVE,
    POSITIVE_FRACTION,
    Choice,
    Each,
    Range,
    check_ranges,
)

Inpaint = Literal["exemplar", "telea", "ns"]

TILE_PX = Range(16, bound="one 16-pixel tile")  # the smallest crop the tiled rasterizer renders


@dataclasses.dataclass(frozen=True)
class RemovalConfig:
    """Removal, R_i = R_obs ∪ R_asset ∪ R_mask ∪ R_enclosed ∪ R_reach (``construct.background.removal``).

    Attributes:
        obs_radius: Gaussians within this of the observed surface Q_i (paper: 3 cm).
        asset_radius: ... within this of the registered asset's surface (paper: 2.4 cm).
        mask_votes: centres inside the expanded bounds projecting inside the instance mask, visible,
            in at least this many views (paper: 2).
        bounds_margin: ours — the expanded bounds are the box of Q_i and the placed asset grown by this.
        mask_views: ours — the instance's largest masks consulted (each is one crop render).
        occlusion_tolerance: ours — a centre more than this behind the depth rendered at its pixel is
            occluded in that view and does not vote (the paper's code has no occlusion test; notes).
        enclosed_directions: ours — R_enclosed: a Gaussian is walled in by the placed asset when a
            horizontal ray meets it in each of this many evenly spread directions (the inside of an
            open container); 0 turns it off. ``enclosed_lift``: the rays also leave from this far (and
            half as far) above the centre, so a floor at the support's height finds the walls.
        reach_sigmas / reach_depth: ours — R_reach: a Gaussian whose longest axis, ``reach_sigmas`` σ
            from its centre, ends more than ``reach_depth`` inside the placed asset (an optimizer's
            needle across the object/support contact, its centre beyond the radii) is removed too:
            kept, its hidden half would show as a streak once the object moves.
        support_band / contact_reach: ours — R_obs ∪ R_asset ∪ R_mask spares the support's own
            surface (Gaussians at most ``support_band`` above the object's support height, or
            below it) farther than ``contact_reach`` across up from the object's contact (its points
            within 2 × ``support_band`` of the support): a draped or soft support is its own
            texture there, and a flat fill is a worse copy of it; 0 spares nothing.
        spare_seen_elsewhere: ours — R_obs ∪ R_asset spares a Gaussian that ``mask_votes`` of the
            mask views saw, unoccluded, outside the instance's mask (it is something else: the
            support around the object, a neighbour, a post in front), unless it is one of the
            object's own visual Gaussians or lies at its contact (within ``support_band`` of the
            support and ``contact_reach`` of the contact and of the placed asset: there a Gaussian
            straddles the masks' edge; given back, the object's rim stayed as ghosts where it
            stood, 15 on seed 7001; without the asset's reach the duvet around snowmiku's plush
            went too, −0.25 → −0.46 dB held out).
        statuses: objects with these statuses are removed; the others stay in the background.
    """

    obs_radius: float = 0.03
    asset_radius: float = 0.024
    mask_votes: int = 2
    bounds_margin: float = 0.02
    mask_views: int = 8
    occlusion_tolerance: float = 0.01
    enclosed_directions: int = 8
    enclosed_lift: float = 0.01
    reach_sigmas: float = 2.0
    reach_depth: float = 0.005
    support_band: float = 0.01
    contact_reach: float = 0.01
    spare_seen_elsewhere: bool = True
    statuses: tuple[str, ...] = ("accepted", "unverified")

    def __post_init__(self):
        check_ranges(self, {
            "obs_radius": NON_NEGATIVE, "asset_radius": NON_NEGATIVE, "mask_votes": AT_LEAST_ONE,
            "bounds_margin": NON_NEGATIVE, "mask_views": AT_LEAST_ONE, "occlusion_tolerance": NON_NEGATIVE,
            "enclosed_directions": NON_NEGATIVE, "enclosed_lift": NON_NEGATIVE, "reach_sigmas": NON_NEGATIVE, "reach_depth": NON_NEGATIVE,
            "support_band": NON_NEGATIVE, "contact_reach": NON_NEGATIVE})


@dataclasses.dataclass(frozen=True)
class CropConfig:
    """Static square crop sizes of the render passes (``construct.background.views``): every crop of
    a pass takes one of these, so the pass compiles once.

    Attributes:
        target_sizes: crop sizes of the target pass, pixels.
        mask_sizes: crop sizes of the R_mask pass, pixels.
        margin_px: pixels around a region (a mask's box, a frame's disks) in its crop.
    """

    target_sizes: tuple[int, ...] = (64, 128)
    mask_sizes: tuple[int, ...] = (64, 128)
    margin_px: int = 8

    def __post_init__(self):
        check_ranges(self, {"target_sizes": Each(TILE_PX), "mask_sizes": Each(TILE_PX), "margin_px": NON_NEGATIVE})


@dataclasses.dataclass(frozen=True)
class PlaneConfig:
    """The support plane of one removed object (``construct.background.plane``).

    Attributes:
        ring_inner: the plane is fitted to kept Gaussian centres at least this far from the object's
            footprint (ours: 1 cm) ...
        ring_outer: ... and at most this far (ours: 8 cm) ...
        ring_height: ... and within this of the object's base height.
        threshold: RANSAC inlier distance (ours: 5 mm).
        ransac_iterations: RANSAC hypotheses (seeded by ``BackgroundConfig.seed``, deterministic).
        max_tilt_deg: a support plane's normal is within this of up.
        base_tolerance: ours — ... and the plane passes this close to the object's base (a table's
            underside has as many ring points; notes).
        min_points: fewer ring points: an unsupported region.
        min_inlier_fraction: fewer inliers than this fraction of the ring: an unsupported region.
        min_opacity: only Gaussians at least this opaque are surface evidence.
    """

    ring_inner: float = 0.01
    ring_outer: float = 0.08
    ring_height: float = 0.025
    threshold: float = 0.005
    ransac_iterations: int = 256
    max_tilt_deg: float = 45.0
    base_tolerance: float = 0.015
    min_points: int = 30
    min_inlier_fraction: float = 0.3
    min_opacity: float = 0.5

    def __post_init__(self):
        check_ranges(self, {
            "ring_inner": NON_NEGATIVE, "ring_outer": Range(self.ring_inner, low_open=True, bound="ring_inner"),
            "ring_height": POSITIVE, "threshold": POSITIVE, "ransac_iterations": AT_LEAST_ONE,
            "max_tilt_deg": ANGLE_DEG, "base_tolerance": NON_NEGATIVE, "min_points": Range(3, bound="a plane"),
            "min_inlier_fraction": FRACTION, "min_opacity": FRACTION})


@dataclasses.dataclass(frozen=True)
class FillConfig:
    """The new disks on the exposed cells (``construct.background.plane``, ``kernels.fill``).

    Attributes:
        grid: disk grid spacing on the plane (paper: 5 mm).
        margin: ours — the fill covers the exposed footprint grown by this (overlaps the kept surface).
        cover_factor: ours — a grid cell is covered by the kept surface when a kept plane Gaussian lies
            within this many times the kept Gaussians' median spacing.
        slab: kept Gaussians within this of the plane are surface (coverage) and are rendered with the
            disks in the refinement; the others are fixed front/back layers.
        disk_sigma: in-plane σ of a new disk as a fraction of ``grid`` (the synthetic capture's disk shape).
        disk_thickness: normal σ of a new disk as a fraction of its in-plane σ (likewise).
        max_disk_sigma: the fit keeps a disk's in-plane σ within [¼, this] × ``grid`` (it bounds the
            pixels a disk can reach, hence the kept Gaussians each step renders).
        init_opacity: of a new disk.
        colour_neighbours: disks no target sees take the mean colour of this many nearest kept plane
            Gaussians ("neighbouring observations").
        max_disks: per object; more is a failed completion (an implausibly large exposed region).
        see_through_votes: ours — a fill cell is not laid where this many training views saw
            surface behind it (``construct.background.seethrough``: past a draped support's edge);
            0 lays every cell.
        see_through_depth: ours — ... more than this behind the cell's centre, metres.
        see_through_views: ours — the views that hold most of an object's cells vote, at most this many.
        see_through_crop: ours — pixels a side of the crop a voting view renders around the cells.
    """

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
    see_through_votes: int = 2
    see_through_depth: float = 0.02
    see_through_views: int = 16
    see_through_crop: int = 128

    def __post_init__(self):
        check_ranges(self, {
            "see_through_votes": NON_NEGATIVE, "see_through_depth": NON_NEGATIVE,
            "see_through_views": AT_LEAST_ONE, "see_through_crop": Range(8),
            "grid": POSITIVE, "margin": NON_NEGATIVE, "cover_factor": POSITIVE, "slab": NON_NEGATIVE,
            "disk_sigma": POSITIVE, "disk_thickness": POSITIVE, "max_disk_sigma": Range(0.25, bound="the lower limit, ¼"),
            "init_opacity": OPEN_FRACTION, "colour_neighbours": AT_LEAST_ONE, "max_disks": AT_LEAST_ONE})


@dataclasses.dataclass(frozen=True)
class TargetsConfig:
    """Inpainting targets (``construct.background.targets``).

    Attributes:
        inpaint: "exemplar" (known patches copied in, continuing the support's texture; ours),
            "telea" (OpenCV's Telea) or "ns" (Navier–Stokes): diffusion, a smooth blend of the border.
        inpaint_radius: OpenCV's inpainting neighbourhood, pixels (telea / ns).
        region_weight: a pixel is in an edit's region where the removed Gaussians' composited weight
            reaches this (their rendered alpha in the capture).
        region_dilate_px: the region is grown by this many pixels.
        loss_ring_px: the fit also covers this many pixels around the region, where the target is the
            kept scene itself (the new disks must not change what was already right).
        explained_alpha: inside the region, a pixel the kept Gaussians cover at least this opaquely, at or
            in front of the support plane (``plane_depth_tolerance``), is kept as rendered, not inpainted.
        plane_depth_tolerance: metres.
        external: ours — a folder of externally edited targets replacing ours (format in
            ``construct.background.targets``); None: our own, made by ``inpaint``.
        write: write the targets (and masks) under ``background/targets/`` for inspection or editing.
    """

    inpaint: Inpaint = "exemplar"
    inpaint_radius: int = 5
    region_weight: float = 0.02
    region_dilate_px: int = 2
    loss_ring_px: int = 4
    explained_alpha: float = 0.95
    plane_depth_tolerance: float = 0.01
    external: str | None = None
    write: bool = True

    def __post_init__(self):
        check_ranges(self, {
            "inpaint": Choice.of(Inpaint), "inpaint_radius": AT_LEAST_ONE, "region_weight": POSITIVE_FRACTION, "region_dilate_px": NON_NEGATIVE,
            "loss_ring_px": NON_NEGATIVE, "explained_alpha": FRACTION, "plane_depth_tolerance": NON_NEGATIVE})


@dataclasses.dataclass(frozen=True)
class RefineConfig:
    """The refinement of the new disks only, the kept Gaussians fixed (``kernels.fill``).

    Attributes:
        iterations: Adam steps.
        dssim_weight: λ of (1 − λ) L1 + λ D-SSIM (3DGS: 0.2).
        lr_colour: learning rate of the SH DC.
        lr_opacity: ... of the opacity logit.
        lr_offset: ... of the in-plane offset (tanh-bounded by one grid cell).
        lr_scale: ... of the in-plane log-scale.
    """

    iterations: int = 40
    dssim_weight: float = 0.2
    lr_colour: float = 0.05
    lr_opacity: float = 0.05
    lr_offset: float = 0.05
    lr_scale: float = 0.02

    def __post_init__(self):
        check_ranges(self, {
            "iterations": NON_NEGATIVE, "dssim_weight": FRACTION, "lr_colour": NON_NEGATIVE,
            "lr_opacity": NON_NEGATIVE, "lr_offset": NON_NEGATIVE, "lr_scale": NON_NEGATIVE})


@dataclasses.dataclass(frozen=True)
class BackgroundConfig:
    """Background branch: coupled source-Gaussian removal, inpainting targets, plane-disk fill.

    Attributes:
        removal: which Gaussians go with each object (R_obs, R_asset, R_mask).
        crops: static crop sizes of the R_mask and target render passes.
        plane: the support plane fitted around each object's footprint.
        fill: the new disks on the exposed cells of that plane.
        targets: the inpainting targets the disks are fitted to.
        refine: the fit of the disks to the targets.
        seed: seeds the RANSAC hypotheses and the asset's surface samples (deterministic runs).
    """

    removal: RemovalConfig = RemovalConfig()
    crops: CropConfig = CropConfig()
    plane: PlaneConfig = PlaneConfig()
    fill: FillConfig = FillConfig()
    targets: TargetsConfig = TargetsConfig()
    refine: RefineConfig = RefineConfig()
    seed: int = 0

    def __post_init__(self):
        check_ranges(self, {"seed": NON_NEGATIVE})
