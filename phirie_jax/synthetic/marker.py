"""A printed fiducial marker lying on the synthetic table top: the scale's truth for ``--marker-size``.

``phirie synth --marker SIDE`` prints one ArUco marker (``DICTIONARY``, id ``MARKER_ID``) whose
black square is SIDE metres on a white sheet (a quiet zone of ``MARGIN_CELLS`` cells around
it), near a corner of the table top, turned by ``YAW`` so its edges are not parallel to the
table's. The sheet is a regular grid of flat, matte disk Gaussians fine enough for the
marker's cells to stay sharp; the table Gaussians under it are left out. Its true corners
(OpenCV's order) are written to ``gt/markers.json``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from phirie_jax.errors import OptionError
from phirie_jax.synthetic.capture import LabelledGaussians, surface_gaussians

DICTIONARY = "DICT_4X4_50"
MARKER_ID = 0
MARGIN_CELLS = 1.5          # white paper around the black square, in marker cells
SAMPLES_PER_CELL = 4        # the sheet's disk spacing is a cell / this
PAPER_LIFT = 0.0005         # the sheet lies this far over the table top (metres)
YAW = np.radians(20.0)
BLACK, WHITE = 0.05, 0.92
TRUTH_FILE = "gt/markers.json"


@dataclasses.dataclass(frozen=True)
class PrintedMarker:
    side: float              # the black square's side (metres)
    centre: np.ndarray       # (3,) world: the sheet's centre on the table top
    yaw: float
    bits: np.ndarray         # (C, C) bool: True where the marker is black (C = its cells, border included)

    @property
    def cell(self) -> float:
        return self.side / len(self.bits)

    @property
    def sheet(self) -> float:
        """The paper's side (metres)."""
        return self.side + 2 * MARGIN_CELLS * self.cell

    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        """World directions of the marker image's x (right) and y (down) axes."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        return np.array([c, s, 0.0]), -np.array([-s, c, 0.0])

    def corners(self) -> np.ndarray:
        """(4, 3) world corners of the black square in OpenCV's order: the image's top-left,
        top-right, bottom-right, bottom-left."""
        right, down = self.axes()
        half = self.side / 2
        return np.array([self.centre + a * half * right + b * half * down
                         for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))])

    def covers(self, xy: np.ndarray) -> np.ndarray:
        """(N,) whether the (N, 2) table points lie under the sheet."""
        right, down = self.axes()
        local = xy - self.centre[:2]
        return ((np.abs(local @ right[:2]) <= self.sheet / 2) & (np.abs(local @ down[:2]) <= self.sheet / 2))

    def colour(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) rgb of the (N, 3) world points on the sheet: black cells, white paper."""
        right, down = self.axes()
        local = points - self.centre
        col = np.floor((local @ right + self.side / 2) / self.cell).astype(int)
        row = np.floor((local @ down + self.side / 2) / self.cell).astype(int)
        n = len(self.bits)
        inside = (col >= 0) & (col < n) & (row >= 0) & (row < n)
        black = np.zeros(len(points), bool)
        black[inside] = self.bits[row[inside], col[inside]]
        return np.repeat(np.where(black, BLACK, WHITE)[:, None], 3, axis=1)

    def gaussians(self, rng: np.random.Generator) -> LabelledGaussians:
        """Flat matte disks on a regular grid over the sheet (label 0: background)."""
        spacing = self.cell / SAMPLES_PER_CELL
        count = int(np.ceil(self.sheet / spacing))
        steps = (np.arange(count) + 0.5) * spacing - self.sheet / 2
        a, b = np.meshgrid(steps, steps, indexing="ij")
        right, down = self.axes()
        points = self.centre + a.reshape(-1, 1) * right + b.reshape(-1, 1) * down
        points[:, 2] += PAPER_LIFT
        normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))
        return surface_gaussians(points, normals, self.colour, points, spacing, 0, 0.0, rng)

    def truth(self) -> dict:
        return {"dictionary": DICTIONARY, "id": MARKER_ID, "side": self.side,
                "corners": self.corners().round(9).tolist()}


def marker_bits() -> np.ndarray:
    """(C, C) bool: the black cells of marker ``MARKER_ID`` of ``DICTIONARY``, border included."""
    import cv2

    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, DICTIONARY))
    cells = dictionary.markerSize + 2
    image = cv2.aruco.generateImageMarker(dictionary, MARKER_ID, cells, borderBits=1)
    return image < 128


def place_marker(side: float, top_extent: np.ndarray, top_z: float, inset: float) -> PrintedMarker:
    """The marker near the table top's (+x, −y) corner, its sheet ``inset`` metres inside the edges."""
    bits = marker_bits()
    probe = PrintedMarker(side, np.zeros(3), YAW, bits)
    reach = probe.sheet / 2 * (abs(np.cos(YAW)) + abs(np.sin(YAW)))  # the turned sheet's half extent
    centre = np.array([top_extent[0] / 2 - inset - reach, -(top_extent[1] / 2 - inset - reach), top_z])
    if np.any(np.abs(centre[:2]) + reach > top_extent / 2):
        raise OptionError("--marker", f"{side} (a sheet of {probe.sheet:.3g} m does not fit on the "
                          f"{' × '.join(f'{v:g}' for v in top_extent)} m table top)")
    return PrintedMarker(side, centre, YAW, bits)
