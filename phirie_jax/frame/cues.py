"""Up from cues that check each other, and the support plane.

Cues, each an up direction with how far it may be off (``sigma_deg``):
- the support plane, as fitted to the opaque Gaussian centres and to the splat-composited
  surface (``phirie_jax.frame.surface``), each from its own points;
- the cameras' level vote (people hold cameras level, to a few degrees);
- plumb lines: the vertical the photos' straight edges agree on (``phirie_jax.frame.lines``);
- a surrounding orbit's up (``phirie_jax.frame.orbit``);
- fiducial markers' plane, when ``--marker-size`` is given (``phirie_jax.frame.markers``).

The support is chosen among the planes of both point sets that lie within
``SUPPORT_SEARCH_DEG`` of the other cues' up and that no camera stands below (a plane cameras
stand below is a wall or a ceiling seen from inside, not what things rest on). In an
object-centric capture the support lies under the point the cameras look at; markers are
printed on it. Up is the weighted mean (1/σ²) of the largest group of cues within
``AGREE_DEG`` of each other; every cue's angle to it is recorded, and a cue farther than
``AGREE_DEG``, or an up that rests on one cue, is a warning.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from phirie_jax.frame.estimate import Plane, angle_deg
from phirie_jax.frame.orbit import Orbit

AGREE_DEG = 10.0            # cues this close corroborate each other; farther apart is a warning
SUPPORT_SEARCH_DEG = 30.0   # a support plane lies this close to the other cues' up
PARALLEL_DEG = 5.0          # planes this close in normal are one orientation
PLANE_SIGMA_DEG = 2.0       # a support plane seen in one point set only
PLANES_AGREE_SIGMA = 2.0    # two point sets' fits of the support: σ = this × the angle between them,
MIN_PLANE_SIGMA_DEG = 0.5   # within these bounds
MAX_PLANE_SIGMA_DEG = 4.0
VOTE_SIGMA_DEG = 5.0        # hand-held cameras are held level to a few degrees
STILL_VOTE_SIGMA_DEG = 10.0  # cameras that barely turn: their mean image up only
SUPPORT_REACH = 0.75        # the orbit's point lies at most this × its distance above its support
LEVEL_GAP = 0.05            # planes this close in height (× the orbit's distance) are one level
MIN_SUPPORT_SHARE = 0.25    # a support under the orbit's point holds this share of the largest candidate's points

SOURCE_WORDS = {"centres": "opaque Gaussian centres", "surface": "splat surface", "markers": "markers"}


@dataclasses.dataclass(frozen=True)
class Cue:
    key: str               # support_centres | support_surface | camera_vote | plumb_lines | orbit | markers
    name: str              # in words
    up: np.ndarray         # (3,) unit, capture coordinates
    sigma_deg: float
    detail: dict = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class UpDecision:
    up: np.ndarray                 # (3,) unit, capture coordinates
    source: str
    support: Plane | None          # capture coordinates
    cues: tuple[Cue, ...]
    used: tuple[str, ...]          # keys of the cues up is the mean of
    warnings: tuple[str, ...]
    evidence: dict


def consensus(cues: list[Cue]) -> tuple[np.ndarray | None, list[Cue]]:
    """The weighted mean up of the heaviest group of cues within ``AGREE_DEG`` of each other
    (grown from each cue in turn), and that group."""
    if not cues:
        return None, []
    weight = {id(c): 1.0 / c.sigma_deg ** 2 for c in cues}
    best, best_weight = [], -1.0
    for seed in cues:
        group = [c for c in cues if angle_deg(c.up, seed.up) <= AGREE_DEG]
        total = sum(weight[id(c)] for c in group)
        if total > best_weight + 1e-12:
            best, best_weight = group, total
    up = None
    for _ in range(3):
        up = np.sum([weight[id(c)] * c.up for c in best], axis=0)
        up /= np.linalg.norm(up)
        regrouped = [c for c in cues if angle_deg(c.up, up) <= AGREE_DEG]
        if {id(c) for c in regrouped} == {id(c) for c in best}:
            break
        best = regrouped or best
    return up, best


def choose_support(planes: list[Plane], reference: np.ndarray, orbit: Orbit | None, marker_plane: Plane | None,
                   threshold: float) -> tuple[Plane | None, dict[int, str]]:
    """The support among ``planes`` (capture coordinates) and why each other plane is not it."""
    why: dict[int, str] = {}
    candidates = []
    for p in planes:
        tilt = angle_deg(p.normal, reference)
        if tilt > SUPPORT_SEARCH_DEG:
            why[id(p)] = f"{tilt:.1f}° from the other cues' up"
        elif p.cameras_below:
            why[id(p)] = f"{p.cameras_below} camera(s) stand below it"
        else:
            candidates.append(p)
    if marker_plane is not None:
        on_markers = [p for p in candidates if angle_deg(p.normal, marker_plane.normal) <= PARALLEL_DEG
                      and abs(p.normal @ marker_plane.centroid - p.offset) <= 2 * threshold]
        chosen = max(on_markers, key=lambda p: p.inliers) if on_markers else marker_plane
    elif not candidates:
        return None, why
    elif orbit is not None and orbit.is_orbit:
        # under the orbit's point: the highest level (a table top over the floor), and on that
        # level the largest plane (a duvet's bumps are planes of their own)
        largest = max(p.inliers for p in candidates)
        gap = {id(p): float(p.normal @ orbit.centre - p.offset) for p in candidates}
        under = [p for p in candidates if p.inliers >= MIN_SUPPORT_SHARE * largest
                 and 0 < gap[id(p)] <= SUPPORT_REACH * orbit.distance]
        if under:
            nearest = min(gap[id(p)] for p in under)
            level = [p for p in under if gap[id(p)] <= nearest + LEVEL_GAP * orbit.distance]
            chosen = max(level, key=lambda p: p.inliers)
        else:
            chosen = max(candidates, key=lambda p: p.inliers)
    else:
        chosen = max(candidates, key=lambda p: p.inliers)
    for p in candidates:
        if p is not chosen:
            why[id(p)] = "another plane is the support"
    return chosen, why


def support_cues(support: Plane, planes: list[Plane]) -> list[Cue]:
    """One cue per point set (centres, surface) with planes parallel to the support: their
    normals weighted by inliers. (Markers are a cue of their own.)"""
    found = {}
    for source in ("centres", "surface"):
        parallel = [p for p in planes if p.source == source and not p.cameras_below
                    and angle_deg(p.normal, support.normal) <= PARALLEL_DEG]
        if parallel:
            normal = np.sum([p.normal * p.inliers for p in parallel], axis=0)
            found[source] = (normal / np.linalg.norm(normal), parallel)
    sigma = PLANE_SIGMA_DEG
    if len(found) == 2:  # two fits of one flat support agree; a soft or bumpy one's do not
        between = angle_deg(found["centres"][0], found["surface"][0])
        sigma = float(np.clip(PLANES_AGREE_SIGMA * between, MIN_PLANE_SIGMA_DEG, MAX_PLANE_SIGMA_DEG))
    return [Cue(f"support_{source}", f"support plane ({SOURCE_WORDS[source]})", normal, sigma,
                {"planes": len(parallel), "points": int(sum(p.inliers for p in parallel))})
            for source, (normal, parallel) in found.items()]


def decide_up(gravity_cues: list[Cue], planes: list[Plane], orbit: Orbit | None, marker_plane: Plane | None,
              threshold: float, given: tuple[np.ndarray, str] | None = None) -> UpDecision:
    """Up, its source, the support and the evidence, from the cues that are not planes
    (``gravity_cues``: vote, plumb lines, orbit) and the planes of both point sets."""
    reference, _ = consensus(gravity_cues)
    if given is not None:
        reference = given[0]
    support, why = (choose_support(planes, reference, orbit, marker_plane, threshold) if reference is not None
                    else (None, {}))
    cues = gravity_cues + (support_cues(support, planes) if support is not None else [])
    if given is not None:
        up, used = given[0], []
        source = given[1]
    else:
        up, used = consensus(cues)
        used = sorted(used, key=lambda c: c.sigma_deg)  # the weightiest first
        if up is None:
            up, source = np.array([0.0, 0.0, 1.0]), "default +z (no cue)"
        else:
            source = " + ".join(c.name for c in used)
    angles = {c.key: angle_deg(c.up, up) for c in cues}
    used_keys = tuple(c.key for c in used)
    warnings = []
    far = [c for c in cues if angles[c.key] > AGREE_DEG]
    if far:
        by = f"the given up ({source})" if given is not None else " + ".join(c.name for c in used)
        warnings.append("up cues disagree: " + "; ".join(f"{c.name} is {angles[c.key]:.1f}° from {by}" for c in far))
    if given is None and len(used) == 1:
        warnings.append(f"up rests on {used[0].name} alone (no other cue within {AGREE_DEG:.0f}° of it): nothing "
                        "checks it; pass --up, or print a marker and pass --marker-size")
    if given is None and used:
        source += f" (cues within {max(angles[k] for k in used_keys):.1f}° of it)"
    pairs = [angle_deg(a.up, b.up) for i, a in enumerate(cues) for b in cues[i + 1:]]
    evidence = {
        "cues": [{"key": c.key, "name": c.name, "up": c.up.round(6).tolist(), "sigma_deg": c.sigma_deg,
                  "angle_to_up_deg": round(angles[c.key], 3), "used": c.key in used_keys, **c.detail} for c in cues],
        "max_disagreement_deg": round(max(pairs), 3) if pairs else 0.0,
        "planes": [{**p.as_dict(), "role": "support" if p is support else why.get(id(p), "")} for p in planes],
    }
    return UpDecision(up, source, support, tuple(cues), used_keys, tuple(warnings), evidence)
