"""Exemplar inpainting: a textured support continues through the hole; nothing else changes."""

import numpy as np
import pytest

from phirie_jax.construct.background.exemplar import exemplar_inpaint
from phirie_jax.construct.background.targets import inpaint

STRIPE_TOLERANCE = 0.02   # mean abs error of a periodic texture continued exactly (float32 copies)


def _stripes(h: int = 48, w: int = 64, period: int = 6) -> np.ndarray:
    """Wood-grain-like horizontal stripes, two colours, a slight slope so rows are not all alike."""
    yy, xx = np.mgrid[0:h, 0:w]
    phase = ((yy + xx // 16) % period) < period // 2
    return np.where(phase[..., None], [0.55, 0.32, 0.15], [0.75, 0.48, 0.25]).astype(np.float32)


def _hole(shape, box) -> np.ndarray:
    hole = np.zeros(shape, bool)
    y0, y1, x0, x1 = box
    hole[y0:y1, x0:x1] = True
    return hole


def test_stripes_continue_through_the_hole_where_diffusion_blurs_them():
    truth = _stripes()
    hole = _hole(truth.shape[:2], (18, 30, 24, 40))
    damaged = np.where(hole[..., None], 0.0, truth)
    ours, left = exemplar_inpaint(damaged, hole)
    assert not left.any()
    blurred = inpaint(damaged, hole, "telea", 5)
    ours_err = np.abs(ours - truth)[hole].mean()
    telea_err = np.abs(blurred - truth)[hole].mean()
    assert ours_err < STRIPE_TOLERANCE
    assert telea_err > 3 * ours_err          # diffusion cannot recover the stripes


def test_known_pixels_are_untouched_and_the_hole_is_filled():
    rng = np.random.default_rng(0)
    image = rng.uniform(0, 1, (32, 40, 3)).astype(np.float32)
    hole = _hole(image.shape[:2], (10, 20, 12, 25)) | _hole(image.shape[:2], (0, 3, 30, 40))  # one at the border
    out, left = exemplar_inpaint(image, hole, patch=5)
    assert not left.any()
    np.testing.assert_array_equal(out[~hole], image[~hole])
    # every filled pixel is a copy of some known pixel
    known = {tuple(v) for v in image[~hole].round(6)}
    assert all(tuple(v) in known for v in out[hole].round(6))


def test_degenerate_inputs():
    image = _stripes(16, 16)
    out, left = exemplar_inpaint(image, np.zeros((16, 16), bool))
    np.testing.assert_array_equal(out, image)
    assert not left.any()
    everything = np.ones((16, 16), bool)
    out, left = exemplar_inpaint(image, everything)     # nothing known to copy
    np.testing.assert_array_equal(out, image)
    assert left.all()
    with pytest.raises(ValueError, match="odd"):
        exemplar_inpaint(image, everything, patch=4)


def test_patches_come_only_from_the_source():
    """Copies come from the support the caller names, never from what stands beside it."""
    truth = _stripes()
    hole = _hole(truth.shape[:2], (18, 30, 24, 40))
    image = np.where(hole[..., None], 0.0, truth)
    image[:, :12] = [0.0, 0.9, 0.0]            # a green object at the left edge: not support
    source = np.ones(hole.shape, bool)
    source[:, :12] = False
    out, left = exemplar_inpaint(image, hole, source)
    assert not left.any()
    assert np.abs(out - truth)[hole].mean() < STRIPE_TOLERANCE
    green = (out[..., 1] > 0.8) & (out[..., 0] < 0.1)
    assert not green[hole].any()
    # the leftover of a hole no source patch reaches is diffused by the stage's inpaint
    nowhere = np.zeros(hole.shape, bool)
    out = inpaint(image, hole, "exemplar", 5, nowhere)
    assert np.isfinite(out).all() and not np.array_equal(out[hole], image[hole])
