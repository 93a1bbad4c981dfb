"""Image health: fouling of the ports and turbid water, told from an empty sea
(trapflow.image_health; docs/image-health.md)."""

from __future__ import annotations

from typing import Annotated

import msgspec

from trapflow.config.base import Section


class ImageHealthConfig(Section):
    """Capture watches one left image now and then against the deployment's first minutes:
    a fouled port (blur, uneven darkening) or turbid water (haze) is flagged on the box, in
    `trapflow status` and in the modem's health record (docs/image-health.md)."""

    enabled: bool = True
    """Watch the images' sharpness, contrast and brightness (about a millisecond a sample)."""
    every_s: Annotated[float, msgspec.Meta(gt=0, le=3600)] = 10.0
    """Seconds of capture time between two sampled pairs."""
    width: Annotated[int, msgspec.Meta(ge=32, le=1024)] = 160
    """Width (pixels) the left image is reduced to before its statistics: detail finer than
    this is not looked at."""
    baseline_s: Annotated[float, msgspec.Meta(gt=0, le=86400)] = 600.0
    """Seconds from the first sample over which the baseline is learnt (the median of each
    statistic); until then the state is `learning`."""
    window_s: Annotated[float, msgspec.Meta(gt=0, le=86400)] = 300.0
    """The statistics compared with the baseline are medians over this many seconds of
    samples: an animal passing or the rig moving is outvoted."""
    hold_s: Annotated[float, msgspec.Meta(ge=0, le=86400)] = 300.0
    """A flag is raised (or cleared) only once its condition has held this long."""
    fouled_below: Annotated[float, msgspec.Meta(gt=0, lt=1)] = 0.5
    """Fouled when sharpness (fine detail for the image's own contrast) falls below this
    share of its baseline."""
    fouled_clear: Annotated[float, msgspec.Meta(gt=0, le=1)] = 0.65
    """A fouled flag clears when sharpness is back above this share of its baseline."""
    turbid_below: Annotated[float, msgspec.Meta(gt=0, lt=1)] = 0.65
    """Turbid when contrast (spread for the brightness) falls below this share of its
    baseline."""
    turbid_clear: Annotated[float, msgspec.Meta(gt=0, le=1)] = 0.8
    """A turbid flag clears when contrast is back above this share of its baseline."""

    def __post_init__(self) -> None:
        if self.fouled_clear <= self.fouled_below:
            raise ValueError("image_health.fouled_clear must be above fouled_below (hysteresis)")
        if self.turbid_clear <= self.turbid_below:
            raise ValueError("image_health.turbid_clear must be above turbid_below (hysteresis)")
