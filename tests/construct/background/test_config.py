"""BackgroundConfig: step configs validate themselves; the paper's defaults are where they were."""

from __future__ import annotations

import pytest

from phirie_jax.construct.background.config import (
    BackgroundConfig,
    CropConfig,
    FillConfig,
    PlaneConfig,
    RefineConfig,
    RemovalConfig,
    TargetsConfig,
)


def test_paper_defaults():
    c = BackgroundConfig()
    assert (c.removal.obs_radius, c.removal.asset_radius, c.removal.mask_votes) == (0.03, 0.024, 2)
    assert c.fill.grid == 0.005 and c.targets.inpaint == "exemplar" and c.refine.dssim_weight == 0.2


@pytest.mark.parametrize("make, message", [
    (lambda: TargetsConfig(inpaint="lama"), "TargetsConfig.inpaint lama: expected one of exemplar, telea, ns"),
    (lambda: RemovalConfig(mask_votes=0), r"RemovalConfig.mask_votes 0: expected ≥ 1"),
    (lambda: FillConfig(init_opacity=1.0), r"FillConfig.init_opacity 1: expected in \(0, 1\)"),
    (lambda: CropConfig(target_sizes=(8,)), r"CropConfig.target_sizes 8: .* ≥ 16 \(one 16-pixel tile\)"),
    (lambda: RefineConfig(iterations=-1), r"RefineConfig.iterations -1: expected ≥ 0"),
    (lambda: PlaneConfig(ring_outer=0.005), r"PlaneConfig.ring_outer 0.005: expected > 0.01 \(ring_inner\)"),
])
def test_invalid_values_are_refused(make, message):
    with pytest.raises(ValueError, match=message):
        make()
