"""Fiducial markers (ArUco, AprilTag) in the photos: metres and up from a printed square.

``--marker-size METRES`` is the side of the markers' black square. Every photo is searched
with OpenCV's ``cv2.aruco`` (the dictionary named by ``--marker-dictionary``, else the common
families in ``DICTIONARIES``; corners refined to sub-pixels, then taken where the square's four
fitted edges meet, ``edge_corners``: a blurred square's corners are rounded and corner detectors
find them inside it, 3–4 % small at 30 px a side; lens distortion undone); each
marker's four corners are triangulated with the cameras of the photos it is seen in (linear
triangulation, views that miss by more than ``MAX_REPROJECTION_PX`` dropped). Its side in
capture units against METRES is the scale; its plane, turned towards the cameras that see it,
is an up cue and a support (markers are printed and laid flat). The uncertainty is the larger
of what the triangulated sides disagree by, what ``CORNER_BIAS_PX`` is of the square's side in
the photos (what is left of that bias where a side gives no clean edge) and ``MIN_BAND``
(printers and rulers).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from phirie_jax.frame.lines import normalized_rays
from phirie_jax.types import Camera

DICTIONARIES = ("DICT_4X4_250", "DICT_5X5_250", "DICT_6X6_250", "DICT_7X7_250", "DICT_ARUCO_ORIGINAL",
                "DICT_APRILTAG_36h11", "DICT_APRILTAG_25h9")
MAX_SIDE = 2048                 # photos are searched at most this large
MAX_REPROJECTION_PX = 3.0
MIN_VIEWS = 2                   # to triangulate at all
GOOD_VIEWS = 3                  # fewer: the scale is announced as weak
MIN_BAND = 1.01                 # ×/÷: a printed marker's side is known to about 1 %
CORNER_BIAS_PX = 0.5            # a blurred square's corners are found up to this far inside it
WEAK_BAND = 1.05                # ×/÷ at least, from fewer than GOOD_VIEWS views
SIGMA_DEG = 1.0                 # the plane of a flat printed marker
EDGE_SPAN = (0.2, 0.8)          # a side's edge is sampled between these fractions of it (corners are rounded)
EDGE_INSIDE, EDGE_OUTSIDE = 0.45, 1.0   # ... across it, from this many cells inside (within the black border) to outside
EDGE_SAMPLES = 33               # samples across the edge
EDGE_CONTRAST = 20.0            # grey levels between the border and the paper for a crossing to count
MAX_EDGE_SHIFT = 0.15           # of the side: fitted corners farther than this from the detected ones are not used


@dataclasses.dataclass(frozen=True)
class Detection:
    view: int
    dictionary: str
    ident: int
    corners: np.ndarray   # (4, 2) pixel coordinates (pixel centres at i + 0.5), ArUco order


@dataclasses.dataclass(frozen=True)
class Marker:
    dictionary: str
    ident: int
    corners: np.ndarray   # (4, 3) capture coordinates
    views: tuple[int, ...]
    reprojection_px: float
    side_px: float        # the square's mean side in the photos (pixels)

    @property
    def edges(self) -> np.ndarray:
        """(4,) the square's sides in capture units."""
        return np.linalg.norm(self.corners - np.roll(self.corners, -1, axis=0), axis=1)

    @property
    def side(self) -> float:
        return float(self.edges.mean())

    def normal(self, cameras: tuple[Camera, ...]) -> np.ndarray:
        """(3,) unit normal of the square, turned towards the cameras that see it."""
        c = self.corners
        n = np.cross(c[2] - c[0], c[3] - c[1])
        n /= np.linalg.norm(n)
        seen_from = np.mean([cameras[v].center for v in self.views], axis=0) - c.mean(0)
        return n if n @ seen_from >= 0 else -n

    def as_dict(self, cameras: tuple[Camera, ...]) -> dict:
        return {"dictionary": self.dictionary, "id": self.ident, "views": len(self.views),
                "side_units": round(self.side, 6), "side_px": round(self.side_px, 1),
                "reprojection_px": round(self.reprojection_px, 3),
                "normal": self.normal(cameras).round(6).tolist(), "corners": self.corners.round(6).tolist()}


def detect(cameras: tuple[Camera, ...], dictionary: str | None = None) -> list[Detection]:
    """Every marker of ``dictionary`` (else of ``DICTIONARIES``) in every readable photo."""
    import cv2

    names = (dictionary,) if dictionary else DICTIONARIES
    detectors = []
    for name in names:
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        dictionary_ = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
        detectors.append((name, cv2.aruco.ArucoDetector(dictionary_, params), dictionary_.markerSize + 2))
    found = []
    for view, camera in enumerate(cameras):
        if camera.image_path is None:
            continue
        image = cv2.imread(str(camera.image_path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            continue
        factor = min(1.0, MAX_SIDE / max(image.shape))
        if factor < 1.0:
            image = cv2.resize(image, None, fx=factor, fy=factor, interpolation=cv2.INTER_AREA)
        to_camera = np.array([camera.width / image.shape[1], camera.height / image.shape[0]])
        grey = image.astype(np.float64)
        for name, detector, cells in detectors:
            corners, ids, _ = detector.detectMarkers(image)
            for quad, ident in zip(corners, [] if ids is None else ids.ravel()):
                refined = edge_corners(grey, quad.reshape(4, 2).astype(np.float64), cells)
                found.append(Detection(view, name, int(ident), (refined + 0.5) * to_camera))
    return found


def edge_corners(grey: np.ndarray, quad: np.ndarray, cells: int) -> np.ndarray:
    """(4, 2) the corners of a detected square ``quad`` (4, 2; OpenCV pixels, centres at
    integers) as the intersections of its four sides, each fitted through where the image
    crosses halfway between the paper's white and the border's black (``grey`` (H, W) float).
    A blurred square's corners are rounded, so corner detectors find them inside it; a straight
    edge's halfway crossing stays where the edge is under any symmetric blur. ``cells``: the
    square's cells along a side (its bits plus the black border), which bounds how far inside
    the border the profile may look. A side that gives too few clean crossings, or corners that
    move more than ``MAX_EDGE_SHIFT`` of the side, leave the detected corners as they were."""
    from scipy.ndimage import map_coordinates

    centre = quad.mean(0)
    side = float(np.mean(np.linalg.norm(quad - np.roll(quad, -1, axis=0), axis=1)))
    cell = side / cells
    lines = []
    for k in range(4):
        start, end = quad[k], quad[(k + 1) % 4]
        along = (end - start) / max(np.linalg.norm(end - start), 1e-9)
        normal = np.array([along[1], -along[0]])
        normal = normal if normal @ ((start + end) / 2 - centre) > 0 else -normal   # outwards
        spots = start + np.outer(np.linspace(EDGE_SPAN[0], EDGE_SPAN[1], max(5, int(side / 2))), end - start)
        offsets = np.linspace(-EDGE_INSIDE * cell, EDGE_OUTSIDE * cell, EDGE_SAMPLES)
        points = spots[:, None, :] + offsets[None, :, None] * normal                # (S, P, 2) x, y
        profile = map_coordinates(grey, [points[..., 1], points[..., 0]], order=1, mode="nearest")
        dark, light = profile.min(axis=1), profile[:, -EDGE_SAMPLES // 4:].mean(axis=1)
        crossings = []
        for row, lo, hi, spot in zip(profile, dark, light, spots):
            if hi - lo < EDGE_CONTRAST:
                continue
            half = 0.5 * (lo + hi)
            darkest = int(np.argmin(row))
            above = np.flatnonzero(row[darkest:] >= half)
            if not len(above) or above[0] == 0:
                continue
            j = darkest + above[0]
            t = (half - row[j - 1]) / max(row[j] - row[j - 1], 1e-9)
            crossings.append(spot + (offsets[j - 1] + t * (offsets[j] - offsets[j - 1])) * normal)
        if len(crossings) < 3:
            return quad
        pts = np.asarray(crossings)
        mean = pts.mean(0)
        direction = np.linalg.svd(pts - mean)[2][0]
        lines.append((mean, direction))
    corners = np.empty((4, 2))
    for k in range(4):            # corner k lies on side k − 1 and side k
        (p, d), (q, e) = lines[k - 1], lines[k]
        matrix = np.array([d, -e]).T
        if abs(np.linalg.det(matrix)) < 1e-6:
            return quad
        a, _ = np.linalg.solve(matrix, q - p)
        corners[k] = p + a * d
    if np.max(np.linalg.norm(corners - quad, axis=1)) > MAX_EDGE_SHIFT * side:
        return quad
    return corners


def triangulate(cameras: tuple[Camera, ...], views: list[int], pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(3,) the point seen at (V, 2) ``pixels`` in ``views`` and (V,) its reprojection errors (pixels)."""
    rows = []
    for view, pixel in zip(views, pixels):
        ray = normalized_rays(cameras[view], pixel[None])[0]
        pose = cameras[view].world_to_camera[:3]
        rows += [ray[0] * pose[2] - pose[0], ray[1] * pose[2] - pose[1]]
    solution = np.linalg.svd(np.asarray(rows))[2][-1]
    point = solution[:3] / solution[3]
    errors = []
    for view, pixel in zip(views, pixels):
        cam = cameras[view]
        local = cam.world_to_camera[:3, :3] @ point + cam.world_to_camera[:3, 3]
        seen = normalized_rays(cam, pixel[None])[0]
        errors.append(cam.K[0, 0] * float(np.linalg.norm(local[:2] / local[2] - seen[:2])))
    return point, np.asarray(errors)


def markers(cameras: tuple[Camera, ...], detections: list[Detection]) -> list[Marker]:
    """Each marker seen in at least ``MIN_VIEWS`` photos, its corners triangulated."""
    groups: dict[tuple[str, int], list[Detection]] = {}
    for d in detections:
        groups.setdefault((d.dictionary, d.ident), []).append(d)
    out = []
    for (name, ident), seen in sorted(groups.items()):
        views = [d.view for d in seen]
        for _ in range(2):  # once with every view, once without those that miss
            if len(set(views)) < MIN_VIEWS:
                break
            chosen = [d for d in seen if d.view in views]
            corners, errors = zip(*(triangulate(cameras, [d.view for d in chosen],
                                                np.array([d.corners[k] for d in chosen])) for k in range(4)))
            worst = np.max(np.asarray(errors), axis=0)
            if (worst <= MAX_REPROJECTION_PX).all():
                side_px = float(np.mean([np.linalg.norm(d.corners - np.roll(d.corners, -1, axis=0), axis=1).mean()
                                         for d in chosen]))
                out.append(Marker(name, ident, np.asarray(corners), tuple(views),
                                  float(np.sqrt(np.mean(np.square(errors)))), side_px))
                break
            views = [v for v, e in zip([d.view for d in chosen], worst) if e <= MAX_REPROJECTION_PX]
    return out


def marker_scale(found: list[Marker], size: float) -> tuple[float, float]:
    """(metres per capture unit, ×/÷ uncertainty) from markers whose side is ``size`` metres."""
    sides = np.concatenate([m.edges / m.side * 1.0 for m in found])        # relative edge lengths
    per_marker = np.array([size / m.side for m in found])
    scale = float(np.median(per_marker))
    spread = np.std(np.r_[sides - 1.0, per_marker / scale - 1.0]) / np.sqrt(max(len(sides), 1))
    corners = 2 * CORNER_BIAS_PX / min(m.side_px for m in found)   # both ends of a side may sit inward
    band = max(MIN_BAND, 1.0 + 2.0 * float(spread), 1.0 + corners)
    if max(len(m.views) for m in found) < GOOD_VIEWS:
        band = max(band, WEAK_BAND)
    return scale, band
