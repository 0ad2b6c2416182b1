"""The robot's settings (``Environment.load(OUT_DIR, robot=RobotConfig(...))``, ``phirie simulate --robot``)."""

from __future__ import annotations

import dataclasses

from phirie_jax.ranges import AT_LEAST_ONE, POSITIVE, Each, Range, check_ranges

DEFAULT_ROBOT = "panda"


@dataclasses.dataclass(frozen=True)
class RobotConfig:
    """A robot merged into a converted scene.

    Attributes:
        model: ``"panda"`` (the Franka Panda shipped in the ``gymnasium-robotics`` wheel:
            ``pip install 'phirie_jax[robot]'``) or the path of an MJCF file whose meshes lie where
            it says (a Menagerie-style robot folder).
        base: (x, y, z, yaw in degrees) of the robot's root body in the scene frame, or None:
            beside the largest support, facing its centre, at the pose that reaches the most
            objects (``placement.default_base``). A base above the floor stands on a box stand.
        end_effector: the MJCF site inverse kinematics drives (None: the model's own, e.g. the
            Panda's ``end_effector``, else the one site whose name says it).
        spacing: Gaussian sample spacing on the links' visual surfaces, m (about one flat disk per
            spacing²).
        shading: strength of the view-dependent lobe that shades each disk by the angle it is seen
            at (the links are drawn from untextured meshes: without it they look flat).
        wrist_camera: add a camera on the hand, looking between the fingers (``env.render("wrist")``).
        wrist_fovy: its vertical field of view, degrees.
        camera_size: (width, height) of images from MJCF and wrist cameras, pixels.
        seed: the surface sampling's seed (the same seed gives the same Gaussians).
    """

    model: str = DEFAULT_ROBOT
    base: tuple[float, float, float, float] | None = None
    end_effector: str | None = None
    spacing: float = 0.006
    shading: float = 0.35
    wrist_camera: bool = True
    wrist_fovy: float = 75.0
    camera_size: tuple[int, int] = (160, 120)
    seed: int = 0

    def __post_init__(self):
        check_ranges(self, {"base": Each(Range(), count=4), "spacing": POSITIVE, "shading": Range(0.0, 2.0),
                            "wrist_fovy": Range(1.0, 170.0), "camera_size": Each(AT_LEAST_ONE, count=2)})
