"""Per-candidate checks and the lexicographic ranking (the paper's selection).

A check table is ``{name: {"value", "threshold", "passed", ...}}`` — the manifest's
``checks`` (docs/architecture.md "Contracts"). ``passed`` is True, False, or None for a check that
has not run: the settling check needs the physics stage's drop test, which fills in
``value``/``passed`` later and re-ranks with ``rank`` (nothing here fakes it).

Ranking key (paper): all checks satisfied, number of failed checks, registration
residual, scale discrepancy, settling displacement (not run ranks after any measured
value), then a deterministic tie-break (pool priority, then name). A check that has not
run neither satisfies nor fails.
"""

from __future__ import annotations

import math

import numpy as np

from phirie_jax.construct.objects.config import ObjectsConfig
from phirie_jax.observe.support import Wall

CHECKS = ("registration", "scale", "support", "collision", "settling", "mount")   # mount: mounted objects only
# Checks an automatically discovered instance (no mask, box or prompt backs it) must pass to be kept:
# a cluster no candidate registers to is a bump, a floater or a fold, not an object.
DISCOVERED_MUST_PASS = ("registration",)
SETTLING_NOT_RUN = "no drop test yet: the physics stage runs it and fills this check in"


def check(value, threshold, passed, **extra) -> dict:
    return {"value": value, "threshold": threshold, "passed": passed, **extra}


def hull_volume(vertices: np.ndarray) -> float:
    """Volume of the convex hull (0 for a flat or degenerate point set)."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        return float(ConvexHull(np.asarray(vertices, np.float64)).volume)
    except (QhullError, ValueError):
        return 0.0


def residual_threshold(observed_size: float, config: ObjectsConfig) -> float:
    """The registration check's bound on E for an object whose observation is ``observed_size``
    across (metres): ``max_residual``, or ``max_relative_residual`` of that size when larger."""
    return max(config.max_residual, config.max_relative_residual * max(observed_size, 0.0))


def candidate_checks(scores: dict, canonical_hull_volume: float, config: ObjectsConfig,
                     observed_size: float = 0.0) -> dict:
    """The check table of one registered hypothesis (``Hypothesis.scores()``) of an observation
    ``observed_size`` across (``register.observed_size``; 0: the absolute bound alone)."""
    energy, support, scale, s0 = scores["energy"], scores["support"], scores["scale"], scores["scale_init"]
    discrepancy = abs(math.log(scale / s0)) if scale > 0 and s0 > 0 else math.inf
    volume = canonical_hull_volume * scale**3
    bound = residual_threshold(observed_size, config)
    return {
        "registration": check(energy, bound, bool(energy <= bound), observed_size=observed_size),
        "scale": check(discrepancy, config.max_scale_discrepancy,
                       bool(discrepancy <= config.max_scale_discrepancy)),
        "support": check(support, config.min_support, bool(support >= config.min_support)),
        "collision": check(volume, config.min_hull_volume, bool(math.isfinite(volume) and volume >= config.min_hull_volume),
                           method="convex hull (stand-in until the physics stage's convex decomposition)"),
        "settling": check(None, config.settle_threshold, None, status="not_run", reason=SETTLING_NOT_RUN),
    }


def mount_of(wall: Wall | None, base_gap: float, config: ObjectsConfig) -> Wall | None:
    """The wall an object is mounted on (``ObjectsConfig.mount_gap``), or None: it hangs (its
    lowest observed point ``base_gap`` metres above the support under it, more than the settling
    threshold) and its Gaussians come within ``mount_gap`` of the ``wall`` behind it."""
    if wall is None or base_gap <= config.settle_threshold or wall.gap > config.mount_gap:
        return None
    return wall


def mount_check(placed: np.ndarray, wall: Wall, config: ObjectsConfig) -> dict:
    """The mount check of a candidate placed at world ``placed`` vertices (V, 3): its asset
    reaches within ``mount_gap`` of the wall it is welded to (value: how far its nearest vertex
    stands in front of the wall, 0 when it touches or enters it)."""
    gap = max(float(np.min(wall.distance(placed))), 0.0) if len(placed) else math.inf
    return check(gap, config.mount_gap, bool(gap <= config.mount_gap),
                 method="nearest point of the placed asset in front of the wall it is welded to",
                 wall_object_gap=round(wall.gap, 4))


def settling_welded(config: ObjectsConfig) -> dict:
    """The settling check of a mounted object's candidate before the physics stage: not run (a
    free drop test would only show that it falls; the physics stage tests the weld)."""
    return check(None, config.settle_threshold, None, status="not_run",
                 reason="mounted: the physics stage welds it to its wall and tests that it holds")


def failed(checks: dict) -> list[str]:
    """Names of the checks that ran and failed."""
    return [name for name, c in checks.items() if c.get("passed") is False]


def not_run(checks: dict) -> list[str]:
    return [name for name, c in checks.items() if c.get("passed") is None]


def _number(value, missing: float = math.inf) -> float:
    return missing if value is None or not math.isfinite(float(value)) else float(value)


def rank_key(entry: dict) -> tuple:
    """Sort key of a candidate record (``checks``, ``priority``, ``name``); lower is better."""
    checks = entry["checks"]
    bad = failed(checks)
    return (len(bad) > 0, len(bad), _number(checks["registration"]["value"]), _number(checks["scale"]["value"]),
            _number(checks.get("settling", {}).get("value")), entry.get("priority", 0), entry["name"])


def rank(entries: list[dict]) -> list[dict]:
    """Valid candidates (those with a check table), best first."""
    return sorted((e for e in entries if e.get("checks")), key=rank_key)


def first_by_priority(entries: list[dict]) -> dict | None:
    """The fixed-priority baseline: the first valid candidate in pool order whose checks all
    pass, else the first valid one."""
    valid = sorted((e for e in entries if e.get("checks")), key=lambda e: (e.get("priority", 0), e["name"]))
    return next((e for e in valid if not failed(e["checks"])), valid[0] if valid else None)


def kept_reason(bad: list[str], base_gap: float | None, settle_threshold: float, mounted: bool = False) -> str | None:
    """Why a kept object is not ``accepted`` (None when it is): its failed checks (``bad``). One
    whose lowest observed point is higher above the support under it (``base_gap``, metres) than the
    settling threshold cannot pass the drop test, since it falls that far: said, for it hangs or
    is mounted (a head on a wall) with no wall found to weld it to (``mounted``: one was)."""
    if not bad:
        return None
    reason = f"kept with failed checks: {', '.join(bad)} (use --strict to reject)"
    if "settling" in bad and base_gap is not None and base_gap > settle_threshold and not mounted:
        reason += (f"; its lowest observed point is {base_gap:.2f} m above the support found under it: it hangs or "
                   "is mounted, and nothing holds it in the simulator")
    return reason


def discovered_rejection(source: str | None, bad: list[str], base_gap: float | None = None,
                         settle_threshold: float = math.inf) -> str | None:
    """Why an instance found by automatic discovery (``source`` "auto") is not kept although its
    best candidate was chosen: it failed one of ``DISCOVERED_MUST_PASS`` (``bad``: the chosen
    candidate's failed checks), or its lowest observed point is higher above the support found
    under it (``base_gap``, metres) than the settling threshold: nothing it stands on was seen
    (a floater, or a fold's crest over a soft support; discovery measures its base against its
    own support plane, which can pass higher there than the surface under it). None keeps it
    (other sources: masks, prompts, are user evidence)."""
    if source != "auto":
        return None
    if base_gap is not None and base_gap > settle_threshold:
        return (f"automatically discovered and its lowest observed point is {base_gap:.3f} m above the support "
                f"found under it (> {settle_threshold} m): it stands on nothing that was seen (a floater, or a "
                "fold of the support)")
    missed = [name for name in DISCOVERED_MUST_PASS if name in bad]
    if not missed:
        return None
    return (f"automatically discovered and failed the {', '.join(missed)} check: no candidate fits what was "
            "observed (an optimiser's bump or floater, or a fold of the support)")
