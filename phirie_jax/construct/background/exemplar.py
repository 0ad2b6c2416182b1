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

A filled patch changes the front, the smoothed hole mask, its normals and the confidence only
near itself, so they are kept as images and recomputed in a window around each filled patch
(``_Front``), not over the whole image at every step: the same numbers as the whole-image
computation (the Gaussian smoothing and the differences are per pixel; the patch confidence is a
sum of 49 float32 values in float64, exact, so it does not depend on where it is computed),
tested against it in ``tests/construct/background/test_exemplar.py``.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

DATA_FLOOR = 1e-3   # keeps flat regions fillable (their isophote term is zero)
NORMAL_SIGMA = 1.0  # px: smoothing of the hole mask before its gradient gives the front's normal


SMOOTH_RADIUS = 4   # px: the support of ``gaussian_filter(…, NORMAL_SIGMA)`` (its truncate 4.0 × σ)


def patch_confidence(confidence: np.ndarray, patch: int, rows: slice = slice(None), cols: slice = slice(None)
                     ) -> np.ndarray:
    """(R, C) float32 mean of ``confidence`` (H, W) over the patch × patch window around each pixel of
    ``rows`` × ``cols`` (mirrored at the image's edges, as ``ndimage.uniform_filter``): summed in
    float64, which holds these sums exactly, so a pixel's value never depends on the window asked."""
    h, w = confidence.shape
    r = patch // 2
    y = np.arange(h)[rows]
    x = np.arange(w)[cols]
    if len(y) == 0 or len(x) == 0:
        return np.zeros((len(y), len(x)), np.float32)
    ys = _mirrored(np.arange(y[0] - r, y[-1] + r + 1), h)
    xs = _mirrored(np.arange(x[0] - r, x[-1] + r + 1), w)
    block = confidence[np.ix_(ys, xs)].astype(np.float64)
    total = np.zeros((len(y), len(x)))
    for dy in range(patch):
        for dx in range(patch):
            total += block[dy:dy + len(y), dx:dx + len(x)]
    return (total / (patch * patch)).astype(np.float32)


def _mirrored(index: np.ndarray, size: int) -> np.ndarray:
    """Indices outside [0, size) mirrored back (d c b a | a b c d | d c b a: ``ndimage``'s "reflect")."""
    period = 2 * size
    index = np.mod(index, period)
    return np.where(index < size, index, period - 1 - index)


class _Front:
    """The fill front and its priorities as images, kept up to date around each filled patch.

    todo, confidence: (H, W) the caller's arrays (the hole left, confidences), changed by it in
    place; gy, gx: (H, W) the isophotes; ``refresh`` after each change recomputes what depends on
    the changed pixels."""

    def __init__(self, todo: np.ndarray, confidence: np.ndarray, gy: np.ndarray, gx: np.ndarray, patch: int):
        self.todo, self.confidence, self.gy, self.gx, self.patch = todo, confidence, gy, gx, patch
        h, w = todo.shape
        self.mask_s = np.zeros((h, w), np.float32)
        self.ny = np.zeros((h, w), np.float32)
        self.nx = np.zeros((h, w), np.float32)
        self.conf = np.zeros((h, w), np.float32)
        self.priority = np.full((h, w), -np.inf, np.float32)
        self.refresh(0, h, 0, w)

    def best(self) -> tuple[int, int, float]:
        """Row, column and patch confidence of the highest-priority front pixel (the first in row-major
        order among equals)."""
        y, x = np.unravel_index(int(np.argmax(self.priority)), self.priority.shape)
        return int(y), int(x), float(self.conf[y, x])

    def refresh(self, y0: int, y1: int, x0: int, x1: int) -> None:
        """Recompute everything that depends on the pixels [y0, y1) × [x0, x1)."""
        h, w = self.todo.shape
        r = self.patch // 2

        def box(grow: int) -> tuple[slice, slice]:
            return slice(max(0, y0 - grow), min(h, y1 + grow)), slice(max(0, x0 - grow), min(w, x1 + grow))

        # the smoothed mask: its support around the change, computed with that much context again
        out_r, out_c = box(SMOOTH_RADIUS)
        in_r, in_c = box(2 * SMOOTH_RADIUS)
        smooth = ndimage.gaussian_filter(self.todo[in_r, in_c].astype(np.float32), NORMAL_SIGMA)
        self.mask_s[out_r, out_c] = smooth[out_r.start - in_r.start:out_r.stop - in_r.start,
                                           out_c.start - in_c.start:out_c.stop - in_c.start]
        # its normals: one pixel further, from one more pixel of context
        out_r, out_c = box(SMOOTH_RADIUS + 1)
        in_r, in_c = box(SMOOTH_RADIUS + 2)
        ny, nx = _gradient(self.mask_s[in_r, in_c])
        sub = (slice(out_r.start - in_r.start, out_r.stop - in_r.start),
               slice(out_c.start - in_c.start, out_c.stop - in_c.start))
        self.ny[out_r, out_c], self.nx[out_r, out_c] = ny[sub], nx[sub]
        conf_r, conf_c = box(r)
        self.conf[conf_r, conf_c] = patch_confidence(self.confidence, self.patch, conf_r, conf_c)
        # the front and its priorities wherever any of those changed
        out_r, out_c = box(SMOOTH_RADIUS + 1)
        in_r, in_c = box(SMOOTH_RADIUS + 2)
        todo = self.todo[in_r, in_c]
        known = ~todo
        touches = np.zeros_like(todo)
        touches[1:] |= known[:-1]
        touches[:-1] |= known[1:]
        touches[:, 1:] |= known[:, :-1]
        touches[:, :-1] |= known[:, 1:]
        front = (todo & touches)[sub]
        ny, nx = self.ny[out_r, out_c], self.nx[out_r, out_c]
        norm = np.hypot(nx, ny) + 1e-12
        data = np.abs(-self.gy[out_r, out_c] * nx + self.gx[out_r, out_c] * ny) / norm + DATA_FLOOR
        self.priority[out_r, out_c] = np.where(front, self.conf[out_r, out_c] * data, -np.inf)


def _gradient(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.gradient`` along rows and columns; an axis of one pixel has none (zeros)."""
    grads = [np.gradient(image, axis=a) if image.shape[a] > 1 else np.zeros_like(image) for a in (0, 1)]
    return grads[0], grads[1]


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
    gy, gx = _gradient(np.where(todo, ndimage.uniform_filter(grey, 3), grey))
    front = _Front(todo, confidence, gy, gx, patch)
    while todo.any():
        y, x, conf = front.best()
        y0, y1, x0, x1 = max(0, y - r), min(h, y + r + 1), max(0, x - r), min(w, x + r + 1)
        target, known = out[y0:y1, x0:x1], ~todo[y0:y1, x0:x1]
        best = _best_source(out, ~allowed, target, known, (y0, x0), search)
        if best is None:
            break
        sy, sx = best
        fill = todo[y0:y1, x0:x1]
        target[fill] = out[sy:sy + (y1 - y0), sx:sx + (x1 - x0)][fill]
        confidence[y0:y1, x0:x1][fill] = conf
        todo[y0:y1, x0:x1] = False
        # the isophotes stay those of the image as given (its hole smoothed): the filled pixels'
        # own gradients are not fed back (they never were: the update read the cleared hole mask)
        front.refresh(y0, y1, x0, x1)
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
