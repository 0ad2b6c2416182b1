"""How a capture's own frame becomes the world: which way is up, and metres per capture unit.

Given on the command line (``--up``, ``--scale``, ``--known-size``, ``--known-distance``,
``--metric``, ``--marker-size``) or declared once in the scene folder's ``frame.json`` (the same keys, e.g.
``{"metric": true, "up": "+z"}``); the command line wins. What is not given is estimated
(``phirie_jax.frame.estimate``) and recorded as an estimate with its uncertainty.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Literal

import numpy as np

from phirie_jax.errors import OptionError, SceneInputError
from phirie_jax.io.jsonfile import read_json_object

SCENE_FRAME_FILE = "frame.json"
Axis = Literal["+x", "-x", "+y", "-y", "+z", "-z"]
AXES: dict[Axis, tuple[int, int, int]] = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}


@dataclasses.dataclass(frozen=True)
class FrameConfig:
    """What the user knows about the capture's frame (everything else is estimated).

    Attributes:
        up: the capture's up as a signed axis: +x, -x, +y, -y, +z or -z, e.g. ``--up=-y``
            (None: estimated from the support plane and the cameras).
        scale: metres per capture unit.
        known_size: ``ID=METRES``: the longest side of instance ID's observed points is METRES.
            The scene is observed once at the estimated scale, then again at the corrected one.
        known_distance: ``X0 Y0 Z0 X1 Y1 Z1 METRES``: two points in capture coordinates and
            the distance between them in metres.
        metric: the capture is already in metres (ARKit, Polycam, ScanNet++ …); ScanNet++
            folders are recognised without it.
        marker_size: the side in metres of the black square of the ArUco/AprilTag markers printed
            and laid in the scene (e.g. 0.05): they are found in the photos, triangulated, and
            give the scale; their plane gives up.
        marker_dictionary: the markers' OpenCV dictionary, e.g. DICT_4X4_50 or
            DICT_APRILTAG_36h11 (default: the common families are all searched).
    """

    up: Axis | None = None
    scale: float | None = None
    known_size: str | None = None
    known_distance: tuple[float, float, float, float, float, float, float] | None = None
    metric: bool = False
    marker_size: float | None = None
    marker_dictionary: str | None = None

    def checked(self) -> FrameConfig:
        """The config itself when every option is usable; else ``OptionError`` naming the option."""
        if self.up is not None and self.up not in AXES:
            raise OptionError("--up", f"{self.up!r} (expected one of {', '.join(AXES)})")
        if self.scale is not None and not (math.isfinite(self.scale) and self.scale > 0):
            raise OptionError("--scale", f"{self.scale} (expected a positive number of metres per capture unit)")
        if self.known_size is not None:
            self.known_size_of()
        if self.known_distance is not None:
            values = np.asarray(self.known_distance, np.float64)
            if values.shape != (7,) or not np.isfinite(values).all():
                raise OptionError("--known-distance", f"{self.known_distance} (expected X0 Y0 Z0 X1 Y1 Z1 METRES)")
            if values[6] <= 0 or np.linalg.norm(values[3:6] - values[:3]) <= 0:
                raise OptionError("--known-distance", "expected two different points and a positive distance in metres")
        if self.marker_size is not None and not (math.isfinite(self.marker_size) and self.marker_size > 0):
            raise OptionError("--marker-size", f"{self.marker_size} (expected the markers' side in metres, e.g. 0.05)")
        if self.marker_dictionary is not None and not valid_dictionary(self.marker_dictionary):
            raise OptionError("--marker-dictionary", f"{self.marker_dictionary!r} (expected an OpenCV ArUco "
                              "dictionary such as DICT_4X4_50, DICT_6X6_250 or DICT_APRILTAG_36h11)")
        if self.marker_dictionary is not None and self.marker_size is None:
            raise OptionError("--marker-dictionary", "given without --marker-size")
        given = [name for name, on in (("--scale", self.scale is not None), ("--known-size", self.known_size),
                                       ("--known-distance", self.known_distance is not None),
                                       ("--metric", self.metric), ("--marker-size", self.marker_size is not None))
                 if on]
        if len(given) > 1:
            raise OptionError(given[1], f"given with {given[0]} (expected one way to set the scale)")
        return self

    def known_size_of(self) -> tuple[int, float] | None:
        """(instance id, metres) of ``known_size``, or None."""
        if self.known_size is None:
            return None
        ident, sep, metres = self.known_size.partition("=")
        try:
            ident_i, metres_f = int(ident), float(metres)
        except ValueError:
            ident_i, metres_f = -1, float("nan")
        if not sep or ident_i < 0 or not (math.isfinite(metres_f) and metres_f > 0):
            raise OptionError("--known-size", f"{self.known_size!r} (expected ID=METRES, e.g. 3=0.12)")
        return ident_i, metres_f

    @property
    def up_axis(self) -> np.ndarray | None:
        return None if self.up is None else np.asarray(AXES[self.up], np.float64)


def valid_dictionary(name: str) -> bool:
    """Whether OpenCV's ``cv2.aruco`` has a predefined dictionary of this name."""
    import cv2

    return name.startswith("DICT_") and isinstance(getattr(cv2.aruco, name, None), int)


def scene_frame_config(root: Path) -> FrameConfig:
    """The scene folder's own declaration (``frame.json``), or an empty config."""
    path = Path(root) / SCENE_FRAME_FILE
    if not path.is_file():
        return FrameConfig()
    data = read_json_object(path)
    fields = {f.name for f in dataclasses.fields(FrameConfig)}
    unknown = sorted(set(data) - fields)
    if unknown:
        raise SceneInputError(path, unknown[0], f"unknown key (expected some of {', '.join(sorted(fields))})")
    if "known_distance" in data and data["known_distance"] is not None:
        data["known_distance"] = tuple(data["known_distance"])
    try:
        return FrameConfig(**data).checked()
    except (OptionError, TypeError) as err:
        field = err.option.lstrip("-").replace("-", "_") if isinstance(err, OptionError) else None
        raise SceneInputError(path, field, getattr(err, "problem", str(err))) from None


def merged(declared: FrameConfig, given: FrameConfig) -> FrameConfig:
    """The command line's options over the scene folder's: ``up`` separately, the scale as a whole
    (any scale option given replaces the declared one)."""
    scale_given = any(v for v in (given.scale, given.known_size, given.known_distance, given.metric,
                                  given.marker_size))
    scale_from = given.checked() if scale_given else declared.checked()
    return dataclasses.replace(scale_from, up=given.up if given.up is not None else declared.up).checked()
