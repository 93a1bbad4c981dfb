"""The statistics of one image the watch compares with the deployment's baseline.

On a grey copy reduced to `width` pixels (area averaging: sensor noise is averaged away
with it), split into a 3x3 grid of regions:
- sharpness: per region, the variance of the Laplacian over the variance of the grey levels
  (fine detail for the region's own contrast); the median over the regions. A blur (a
  fouled port) takes it away; a veil (turbid water) or a darker image (night, a failing
  lamp) leaves it, since both scale the detail and the spread alike. The median over
  regions is not moved by an animal that fills a few of them.
- contrast: standard deviation over mean of the grey levels (the coefficient of variation).
  A veil toward the water's colour takes it away; a darker image leaves it; a blur barely
  touches it at this scale (the spread is in the large shapes).
- brightness: the mean grey level (reported, never flagged: night is not a fault).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

REGIONS = 3  # the grid is REGIONS x REGIONS
MIN_VARIANCE = 1.0  # grey levels squared: a flat region's sharpness is 0, not noise over 0


@dataclass(frozen=True)
class Sample:
    """One image's statistics (see the module's docstring)."""

    sharpness: float
    contrast: float
    brightness: float


def measure(img: np.ndarray, width: int = 160) -> Sample:
    """The statistics of a BGR or grey image, reduced to `width` pixels wide first."""
    h, w = img.shape[:2]
    if w > width:
        img = cv2.resize(img, (width, max(1, round(h * width / w))),
                         interpolation=cv2.INTER_AREA)
    grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
    g = grey.astype(np.float32)
    lap = cv2.Laplacian(g, cv2.CV_32F)
    gh, gw = g.shape
    ratios = []
    for i in range(REGIONS):
        for j in range(REGIONS):
            sl = (slice(i * gh // REGIONS, (i + 1) * gh // REGIONS),
                  slice(j * gw // REGIONS, (j + 1) * gw // REGIONS))
            var = float(cv2.meanStdDev(g[sl])[1][0, 0]) ** 2
            detail = float(cv2.meanStdDev(lap[sl])[1][0, 0]) ** 2
            ratios.append(detail / var if var >= MIN_VARIANCE else 0.0)
    mean_, std_ = cv2.meanStdDev(g)
    mean, std = float(mean_[0, 0]), float(std_[0, 0])
    return Sample(sharpness=float(np.median(ratios)),
                  contrast=std / mean if mean > 0 else 0.0, brightness=mean)
