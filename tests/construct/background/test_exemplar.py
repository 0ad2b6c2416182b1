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


def _reference(image, hole, source=None, patch=7, search=40):
    """The algorithm recomputed over the whole image at every step (the slow reference of the
    windowed front): front, smoothed mask, normals and patch confidences from scratch."""
    from scipy import ndimage

    from phirie_jax.construct.background.exemplar import DATA_FLOOR, NORMAL_SIGMA, _best_source, patch_confidence

    out = np.clip(np.asarray(image, np.float32), 0.0, 1.0).copy()
    todo = np.asarray(hole, bool).copy()
    allowed = ~todo if source is None else (np.asarray(source, bool) & ~todo)
    if not todo.any() or not allowed.any():
        return out, todo
    h, w = todo.shape
    r = patch // 2
    confidence = (~todo).astype(np.float32)
    grey = out.mean(-1)
    gy, gx = np.gradient(np.where(todo, ndimage.uniform_filter(grey, 3), grey))
    while todo.any():
        front = todo & ndimage.binary_dilation(~todo)
        ys, xs = np.nonzero(front)
        ny, nx = np.gradient(ndimage.gaussian_filter(todo.astype(np.float32), NORMAL_SIGMA))
        norm = np.hypot(nx[ys, xs], ny[ys, xs]) + 1e-12
        data = np.abs(-gy[ys, xs] * nx[ys, xs] + gx[ys, xs] * ny[ys, xs]) / norm + DATA_FLOOR
        conf = patch_confidence(confidence, patch)[ys, xs]
        k = int(np.argmax(conf * data))
        y, x = int(ys[k]), int(xs[k])
        y0, y1, x0, x1 = max(0, y - r), min(h, y + r + 1), max(0, x - r), min(w, x + r + 1)
        target, known = out[y0:y1, x0:x1], ~todo[y0:y1, x0:x1]
        best = _best_source(out, ~allowed, target, known, (y0, x0), search)
        if best is None:
            break
        sy, sx = best
        fill = todo[y0:y1, x0:x1]
        target[fill] = out[sy:sy + (y1 - y0), sx:sx + (x1 - x0)][fill]
        confidence[y0:y1, x0:x1][fill] = conf[k]
        todo[y0:y1, x0:x1] = False
    return out, todo


@pytest.mark.parametrize("seed", range(4))
def test_the_windowed_front_equals_the_whole_image_recomputation(seed):
    rng = np.random.default_rng(seed)
    h, w = 40 + 8 * seed, 56
    yy, xx = np.mgrid[0:h, 0:w]
    image = np.stack([0.5 + 0.4 * np.sin(xx / (3 + seed) + yy / 7), rng.uniform(0, 1, (h, w)),
                      (yy % 5 < 2) * 0.6 + 0.2], -1).astype(np.float32)
    hole = (yy - rng.uniform(10, h - 10)) ** 2 / 90 + (xx - rng.uniform(0, w)) ** 2 / 160 < 1   # may touch an edge
    hole |= (yy < 4) & (xx > w - 10)                                                            # a corner too
    source = None if seed % 2 else ~hole & (xx < w - 3)
    ours, left = exemplar_inpaint(image, hole, source)
    ref, ref_left = _reference(image, hole, source)
    np.testing.assert_array_equal(ours, ref)
    np.testing.assert_array_equal(left, ref_left)


def test_patch_confidence_is_the_mirrored_box_mean_wherever_it_is_asked():
    from scipy import ndimage

    from phirie_jax.construct.background.exemplar import patch_confidence

    conf = np.random.default_rng(0).uniform(0.05, 1, (23, 31)).astype(np.float32)
    whole = patch_confidence(conf, 7)
    np.testing.assert_allclose(whole, ndimage.uniform_filter(conf, 7), rtol=1e-6)   # scipy's, to its rounding
    np.testing.assert_array_equal(patch_confidence(conf, 7, slice(2, 9), slice(20, 31)), whole[2:9, 20:31])


def test_the_fronts_images_after_each_fill_equal_their_whole_image_recomputation():
    from phirie_jax.construct.background.exemplar import _Front

    rng = np.random.default_rng(5)
    h, w = 37, 45
    todo = np.zeros((h, w), bool)
    todo[5:30, 8:40] = True
    confidence = (~todo).astype(np.float32)
    gy, gx = (rng.normal(size=(h, w)).astype(np.float32) for _ in range(2))
    front = _Front(todo, confidence, gy, gx, 7)
    for _ in range(12):
        y, x, conf = front.best()
        y0, y1, x0, x1 = max(0, y - 3), min(h, y + 4), max(0, x - 3), min(w, x + 4)
        confidence[y0:y1, x0:x1][todo[y0:y1, x0:x1]] = conf
        todo[y0:y1, x0:x1] = False
        front.refresh(y0, y1, x0, x1)
        fresh = _Front(todo, confidence, gy, gx, 7)
        for name in ("mask_s", "ny", "nx", "conf", "priority"):
            np.testing.assert_array_equal(getattr(front, name), getattr(fresh, name), err_msg=name)
