"""A dependency-free mono detector: reddish blobs on the sea floor, reported as crabs.

A real, cheap algorithm (HSV threshold + contours) for machines without a model.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import cv2
import msgspec
import numpy as np

from trapflow.plugin import Context, Detection, MonoIR, Pair, Worker, WorkerError


class BlobParams(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """Parameters of the blob detector."""

    min_area_px: int = 150
    max_detections: int = 20
    label: str = "crab"
    scale: float = 0.5  # work on a downscaled image: 4x fewer pixels, same boxes


class BlobDetector(Worker):
    """Contours of saturated reddish regions, boxed and scored by fill ratio."""

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        try:
            self.p = msgspec.convert(dict(params), BlobParams)
        except msgspec.ValidationError as exc:
            raise WorkerError(f"pools.{ctx.pool}.params: {exc}") from None

    def process(self, pair: Pair) -> MonoIR:
        s = self.p.scale
        img = cv2.resize(pair.left, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
        hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)
        # Red wraps around hue 0 in OpenCV's 0..180 hue scale.
        mask = cv2.bitwise_or(cv2.inRange(hsv, (0, 90, 40), (12, 255, 255)),
                              cv2.inRange(hsv, (165, 90, 40), (180, 255, 255)))
        mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        dets: list[Detection] = []
        for c in contours:
            area = cv2.contourArea(c) / (s * s)
            if area < self.p.min_area_px:
                continue
            x, y, w, h = cv2.boundingRect(c)
            fill = area / max(w * h / (s * s), 1.0)
            box = (x / s, y / s, (x + w) / s, (y + h) / s)
            dets.append(Detection(label=self.p.label, confidence=min(1.0, 0.3 + 0.7 * fill),
                                  box=box))
        dets.sort(key=lambda d: d.confidence, reverse=True)
        return MonoIR(detections=dets[: self.p.max_detections])
