"""``report.html``'s settings (``phirie convert --config.report.FIELD``)."""

from __future__ import annotations

import dataclasses

from phirie_jax.ranges import AT_LEAST_ONE, FRACTION, NON_NEGATIVE, Each, check_ranges


@dataclasses.dataclass(frozen=True)
class ReportConfig:
    """What ``report.html`` renders. Its cost is a few small renders: one compile per Gaussian
    bucket and image size (before, after, thumbnails), then milliseconds to a second per image.

    Attributes:
        enabled: write ``report.html`` at the end of a conversion.
        views: cameras rendered before and after conversion (spread evenly over the capture's).
        width: the widest render in pixels: a camera renders at its own width up to this (height
            follows its aspect). At a camera's own size the rollout's compiled renderer is reused.
        thumbnail: side of each object's square thumbnail in pixels (the converted scene at t = 0
            from the camera that sees the object largest, cropped to it).
        filmstrip: rollout frames inlined when a rollout is given (the video itself is linked).
        background: colour behind the Gaussians, rgb in [0, 1].
    """

    enabled: bool = True
    views: int = 3
    width: int = 320
    thumbnail: int = 96
    filmstrip: int = 6
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def __post_init__(self):
        check_ranges(self, {"views": NON_NEGATIVE, "width": AT_LEAST_ONE, "thumbnail": AT_LEAST_ONE,
                            "filmstrip": NON_NEGATIVE, "background": Each(FRACTION, count=3)})
