"""How prompts (a box or a click in one photo) become objects: ``ObserveConfig.prompts``."""

from __future__ import annotations

import dataclasses

from phirie_jax.ranges import (
    ANGLE_DEG,
    AT_LEAST_ONE,
    FRACTION,
    NON_NEGATIVE,
    POSITIVE,
    POSITIVE_FRACTION,
    Range,
    at_least,
    check_ranges,
)


@dataclasses.dataclass(frozen=True)
class PromptConfig:
    """Prompts lifted to objects (``--prompt``, ``prompts.json``; ``observe/prompt_lift.py``). Ours,
    beyond the paper (it takes its masks as given). Lengths in metres are those of the scene frame.

    Attributes:
        min_alpha: prompt-view pixels with less rendered alpha show nothing to seed from.
        min_opacity: Gaussians at least this opaque (and not floaters) are what an object is made
            of and what it grows over; the more transparent ones near it follow it into its masks.
        centre_fraction: a box's seed window is its middle, this fraction of its width and height.
        click_radius: a click's seed window is a disk of this radius, as a fraction of the image's
            width (at least 1.5 pixels).
        depth_bin: bin of the log-depth histogram whose peak is the seed's depth (the dominant
            depth cluster near the box's centre: the object, not the background between its parts).
        depth_band: seed pixels lie within this of the peak (log depth, i.e. a fraction).
        seed_behind: a pixel's Gaussians are the opaque ones from 1 % in front of its rendered depth
            to this fraction behind it (the rendered depth of a real capture sits in front of the
            surface: semi-transparent haze pulls it towards the camera, 1–3 cm on snowmiku)...
        seed_behind_max: ... and at most this far (metres): a small object far away would
            otherwise take the table behind it.
        link_factor: Gaussians closer than this × the seed's typical spacing (distance to the
            ``link_neighbours``-th neighbour) are connected; the object is what connects to the seed.
        link_neighbours: the spacing is measured to this many-th nearest neighbour.
        extent_factor: a Gaussian also touches what lies within this × its largest standard
            deviation (large Gaussians of a real capture stand far apart)...
        max_link_factor: ... up to this × the link radius.
        attach_factor: a semi-transparent Gaussian within this × the link radius of an object's
            opaque one belongs to the object's masks.
        box_margin: the object may reach this fraction of the box's size past the box (in its view).
        reach: the object lies within this × the box's half-diagonal (at the seed's depth) of the seed.
        ring: the background around the box is seen in a ring this fraction of the box's size wide.
        plane_threshold: background plane inlier distance, as a fraction of the seed's depth.
        min_plane_fraction: a background plane holds at least this fraction of the ring's Gaussians.
        max_planes: background planes fitted to the ring (walls, the support, furniture).
        support_tilt_deg: the support's Gaussians are flat and face up within this angle.
        support_bin: height bin of the support's histogram (metres).
        min_support_gaussians: a support needs this many flat, up-facing Gaussians under the object.
        support_band_min: the object starts at least this far above its support's height...
        support_band_max: ... and at most this far: within these, the support's own spread (a
            crumpled duvet is thicker than a table).
        click_reach: a click whose depth-connected region leaks over most of the photo is taken to
            mark an object at most this far (metres) across.
        flood_jump: a click's region grows over neighbouring pixels whose log depth differs less.
        max_flood_fraction: a click's region larger than this fraction of the photo has leaked.
        open_px: side of the square kernel of the masks' morphological open (0 or 1 = none).
        close_px: side of the square kernel of the masks' morphological close (0 or 1 = none).
        min_component: pieces of a mask smaller than this fraction of its largest piece are dropped.
    """

    min_alpha: float = 0.5
    min_opacity: float = 0.1
    centre_fraction: float = 0.34
    click_radius: float = 0.01
    depth_bin: float = 0.02
    depth_band: float = 0.04
    seed_behind: float = 0.08
    seed_behind_max: float = 0.03
    link_factor: float = 6.0
    link_neighbours: int = 4
    extent_factor: float = 2.0
    max_link_factor: float = 4.0
    attach_factor: float = 3.0
    box_margin: float = 0.05
    reach: float = 1.5
    ring: float = 0.12
    plane_threshold: float = 0.01
    min_plane_fraction: float = 0.15
    max_planes: int = 3
    support_tilt_deg: float = 30.0
    support_bin: float = 0.005
    min_support_gaussians: int = 12
    support_band_min: float = 0.005
    support_band_max: float = 0.01
    click_reach: float = 0.3
    flood_jump: float = 0.03
    max_flood_fraction: float = 0.5
    open_px: int = 3
    close_px: int = 5
    min_component: float = 0.2

    def __post_init__(self):
        check_ranges(self, {
            "min_alpha": POSITIVE_FRACTION, "min_opacity": FRACTION, "centre_fraction": POSITIVE_FRACTION,
            "click_radius": POSITIVE_FRACTION, "depth_bin": POSITIVE, "depth_band": POSITIVE, "seed_behind": POSITIVE,
            "seed_behind_max": POSITIVE,
            "link_factor": POSITIVE, "link_neighbours": AT_LEAST_ONE, "extent_factor": NON_NEGATIVE,
            "max_link_factor": Range(1), "attach_factor": POSITIVE,
            "box_margin": NON_NEGATIVE, "reach": POSITIVE, "ring": POSITIVE, "plane_threshold": POSITIVE,
            "min_plane_fraction": POSITIVE_FRACTION, "max_planes": NON_NEGATIVE, "support_tilt_deg": ANGLE_DEG,
            "support_bin": POSITIVE, "min_support_gaussians": AT_LEAST_ONE, "click_reach": POSITIVE,
            "flood_jump": POSITIVE, "max_flood_fraction": POSITIVE_FRACTION, "open_px": NON_NEGATIVE,
            "close_px": NON_NEGATIVE, "min_component": FRACTION, "support_band_min": NON_NEGATIVE,
            "support_band_max": at_least(self.support_band_min, "support_band_min")})
