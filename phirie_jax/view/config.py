"""The viewer's settings (``phirie view OUT_DIR --config.FIELD``)."""

from __future__ import annotations

import dataclasses

from phirie_jax.ranges import AT_LEAST_ONE, NON_NEGATIVE, POSITIVE, Range, check_ranges

PORTS = Range(0, 65535, bound="0 = any free port")


@dataclasses.dataclass(frozen=True)
class ViewConfig:
    """The web viewer: server, live simulation and interactions.

    Attributes:
        host: address the server listens on; 127.0.0.1 serves this machine only (use 0.0.0.0 to
            serve the network, e.g. a headless workstation viewed from a laptop).
        port: port of the server (0 = any free port; viser moves to the next free one when taken).
        playing: the simulation runs from the start (else it starts paused).
        realtime: simulated seconds per wall second while playing.
        frame_rate: node pose updates sent per second while playing.
        max_substeps: most simulator steps per update (a slow machine then runs slower than
            real time rather than stepping ever larger batches).
        shot_speed: a click gives the object it hits this speed (m/s) along the view ray, like
            ``Environment.shoot`` (impulse = mass × speed at the hit point).
        drag_stiffness: dragging pulls the grabbed point towards the pointer with this acceleration
            per metre of stretch (1/s²): force = mass × stiffness × stretch, critically damped.
        drag_max_acceleration: the drag force is clamped to mass × this (m/s²), so a long stretch
            does not launch the object.
        frustum_scale: drawn size of the capture's camera frustums (m).
    """

    host: str = "127.0.0.1"
    port: int = 8080
    playing: bool = True
    realtime: float = 1.0
    frame_rate: float = 30.0
    max_substeps: int = 60
    shot_speed: float = 1.5
    drag_stiffness: float = 400.0
    drag_max_acceleration: float = 40.0
    frustum_scale: float = 0.04

    def __post_init__(self):
        check_ranges(self, {"port": PORTS, "realtime": POSITIVE, "frame_rate": POSITIVE,
                            "max_substeps": AT_LEAST_ONE, "shot_speed": NON_NEGATIVE, "drag_stiffness": POSITIVE,
                            "drag_max_acceleration": POSITIVE, "frustum_scale": POSITIVE})
