"""The background stage's config (removal, targets, fill): frozen dataclasses whose defaults are the φ-RIE paper's numbers.

Where the paper gives a number it is the default and the field says so ("paper");
every other default is ours and the field says why. Lengths are metres, angles degrees.
"""

from __future__ import annotations

import dataclasses


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
