"""BackgroundConfig: step configs validate themselves; the paper's defaults are where they were."""

from __future__ import annotations

import pytest

from phirie_jax.construct.background.config import (
    BackgroundConfig,
    CropConfig,
    FillConfig,
    RefineConfig,
    RemovalConfig,
    TargetsConfig,
)


def test_paper_defaults():
    c = BackgroundConfig()
    assert (c.removal.obs_radius, c.removal.asset_radius, c.removal.mask_votes) == (0.03, 0.024, 2)
    assert c.fill.grid == 0.005 and c.targets.inpaint == "telea" and c.refine.dssim_weight == 0.2


@pytest.mark.parametrize("make", [
    lambda: TargetsConfig(inpaint="lama"),
    lambda: RemovalConfig(mask_votes=0),
    lambda: FillConfig(init_opacity=1.0),
    lambda: CropConfig(target_sizes=(8,)),
    lambda: RefineConfig(iterations=-1),
])
def test_invalid_values_are_refused(make):
    with pytest.raises(ValueError, match="background"):
        make()
