"""A dependency-free stereo classifier: labels the pair from colour statistics of both views."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import cv2
import msgspec
import numpy as np

from trapflow.plugin import Context, Pair, StereoIR, Worker, WorkerError


class HistogramParams(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """Parameters of the histogram classifier."""

    red_fraction: float = 0.002  # fraction of reddish pixels that makes a 'crab' scene
    size: int = 160  # both views are shrunk to this width first


class HistogramClassifier(Worker):
    """Reddish-pixel fraction, averaged over both views, thresholded into crab / empty."""

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        try:
            self.p = msgspec.convert(dict(params), HistogramParams)
        except msgspec.ValidationError as exc:
            raise WorkerError(f"pools.{ctx.pool}.params: {exc}") from None

    def _red(self, img: np.ndarray) -> float:
        h, w = img.shape[:2]
        small = cv2.resize(img, (self.p.size, max(1, h * self.p.size // w)),
                           interpolation=cv2.INTER_AREA)
        hsv = cv2.cvtColor(small, cv2.COLOR_BGR2HSV)
        mask = cv2.bitwise_or(cv2.inRange(hsv, (0, 90, 40), (12, 255, 255)),
                              cv2.inRange(hsv, (165, 90, 40), (180, 255, 255)))
        return float(np.count_nonzero(mask)) / mask.size

    def process(self, pair: Pair) -> StereoIR:
        frac = (self._red(pair.left) + self._red(pair.right)) / 2
        ratio = frac / self.p.red_fraction
        if ratio >= 1.0:
            return StereoIR(label="crab", confidence=round(min(1.0, 0.5 + 0.1 * ratio), 3))
        return StereoIR(label="empty", confidence=round(1.0 - 0.5 * ratio, 3))
