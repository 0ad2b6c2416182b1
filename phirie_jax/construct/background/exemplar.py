"""Exemplar-based inpainting (Criminisi, Pérez and Toyama 2004): the hole is filled patch by patch
with the best-matching patch of the known image around it (of the support only, where the caller
says which pixels show it), in an order that continues linear structure first.

Diffusion inpainting (OpenCV's Telea / Navier–Stokes) fills a hole with a smooth blend of its
border: on a textured support (wood grain, a tablecloth's weave) the filled patch reads as a
blurred blot where the object stood. Copying known patches continues the texture instead.

Per step: the fill front is the hole pixels touching known ones; each front pixel p has priority
C(p) · D(p), where C is the mean confidence of its patch (1 for captured pixels, inherited for
filled ones) and D = |∇I⊥(p) · n(p)| + ``DATA_FLOOR`` is the strength of the isophote arriving
at the front along its normal n. The highest-priority patch takes, in its hole pixels, the
pixels of the known patch within ``search`` pixels that minimises the SSD over its known pixels
(``cv2.matchTemplate`` with a mask; candidates must be entirely known).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

DATA_FLOOR = 1e-3   # keeps flat regions fillable (their isophote term is zero)
NORMAL_SIGMA = 1.0  # px: smoothing of the hole mask before its gradient gives the front's normal


def exemplar_inpaint(image: np.ndarray, hole: np.ndarray, source: np.ndarray | None = None, patch: int = 7,
                     search: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) float image in [0, 1] with the ``hole`` (H, W) bool pixels filled by known patches,
    and (H, W) bool the hole pixels left unfilled (no source patch anywhere in the image).

    source: (H, W) bool, where source patches may come from (default: every pixel outside the
    hole); a patch must lie entirely in it. patch: odd patch side, pixels. search: half side of
    the window searched around the patch being filled (doubled while it holds no candidate).
    Pixels outside the hole are returned unchanged.
    """
    if patch % 2 == 0 or patch < 3:
        raise ValueError(f"exemplar patch side {patch} (expected an odd number ≥ 3)")
    out = np.clip(np.asarray(image, np.float32), 0.0, 1.0).copy()
    todo = np.asarray(hole, bool).copy()
    allowed = ~todo if source is None else (np.asarray(source, bool) & ~todo)
    if not todo.any() or not allowed.any():
        return out, todo
    h, w = todo.shape
    r = patch // 2
    confidence = (~todo).astype(np.float32)
    grey = out.mean(-1)
    # isophotes, the hole's own content (what the kept render left there) smoothed first
    gy, gx = np.gradient(np.where(todo, ndimage.uniform_filter(grey, 3), grey))
    while todo.any():
        front = todo & ndimage.binary_dilation(~todo)
        ys, xs = np.nonzero(front)
        mask_s = ndimage.gaussian_filter(todo.astype(np.float32), NORMAL_SIGMA)
        ny, nx = np.gradient(mask_s)
        norm = np.hypot(nx[ys, xs], ny[ys, xs]) + 1e-12
        data = np.abs(-gy[ys, xs] * nx[ys, xs] + gx[ys, xs] * ny[ys, xs]) / norm + DATA_FLOOR
        conf = ndimage.uniform_filter(confidence, patch)[ys, xs]
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
        grey_patch = target.mean(-1)
        gy_p, gx_p = np.gradient(grey_patch) if min(grey_patch.shape) > 1 else (0.0, 0.0)
        gy[y0:y1, x0:x1] = np.where(fill, gy_p, gy[y0:y1, x0:x1])
        gx[y0:y1, x0:x1] = np.where(fill, gx_p, gx[y0:y1, x0:x1])
    return out, todo


def _best_source(image: np.ndarray, forbidden: np.ndarray, target: np.ndarray, known: np.ndarray,
                 corner: tuple[int, int], search: int) -> tuple[int, int] | None:
    """Top-left corner of the patch of ``target``'s shape free of ``forbidden`` pixels, within
    ``search`` pixels of ``corner``, that minimises the SSD over ``known`` pixels; None when the
    image has none."""
    import cv2

    h, w = forbidden.shape
    ph, pw = target.shape[:2]
    template = np.ascontiguousarray(target)
    weights = np.repeat(known[..., None], 3, axis=-1).astype(np.float32)
    while True:
        y0, x0 = max(0, corner[0] - search), max(0, corner[1] - search)
        y1, x1 = min(h, corner[0] + ph + search), min(w, corner[1] + pw + search)
        window = np.ascontiguousarray(image[y0:y1, x0:x1])
        if window.shape[0] >= ph and window.shape[1] >= pw:
            cost = cv2.matchTemplate(window, template, cv2.TM_SQDIFF, mask=weights)
            # a candidate must be entirely known: no hole pixel under it
            valid = _window_sums(forbidden[y0:y1, x0:x1], ph, pw) == 0
            if valid.any():
                cost = np.where(valid & np.isfinite(cost), cost, np.inf)
                iy, ix = np.unravel_index(int(np.argmin(cost)), cost.shape)
                return y0 + int(iy), x0 + int(ix)
        if y0 == 0 and x0 == 0 and y1 == h and x1 == w:
            return None
        search *= 2


def _window_sums(mask: np.ndarray, ph: int, pw: int) -> np.ndarray:
    """(H − ph + 1, W − pw + 1): the number of set pixels of ``mask`` in each ph × pw window, by its
    top-left corner (a summed-area table)."""
    table = np.zeros((mask.shape[0] + 1, mask.shape[1] + 1), np.int64)
    table[1:, 1:] = np.cumsum(np.cumsum(mask, axis=0), axis=1)
    return table[ph:, pw:] - table[:-ph, pw:] - table[ph:, :-pw] + table[:-ph, :-pw]
