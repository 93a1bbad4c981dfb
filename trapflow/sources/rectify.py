"""Stereo rectification with maps computed once from a calibration, applied per pair.

Pinhole lenses use cv2.initUndistortRectifyMap, fisheye lenses cv2.fisheye's.
"""

from __future__ import annotations

import cv2
import numpy as np

from trapflow.calibration.model import StereoCalibration
from trapflow.sources.base import Frames, SkipPair, Source, SourceError


class Rectifier:
    """Remaps left and right images into the rectified geometry of a calibration."""

    def __init__(self, calib: StereoCalibration) -> None:
        self.calib = calib
        size = calib.size
        # initUndistortRectifyMap is the expensive part: done here once, never per pair.
        build = (cv2.fisheye.initUndistortRectifyMap if calib.model == "fisheye"
                 else cv2.initUndistortRectifyMap)
        self._maps = [
            build(calib.arr(k), calib.arr(d), calib.arr(r), calib.arr(p), size, cv2.CV_16SC2)
            for k, d, r, p in (("K1", "D1", "R1", "P1"), ("K2", "D2", "R2", "P2"))
        ]

    def apply(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rectified copies of one pair; SourceError if the size is not the calibrated one."""
        w, h = self.calib.size
        for side, img in (("left", left), ("right", right)):
            if img.shape[1] != w or img.shape[0] != h:
                raise SourceError(
                    f"rectify: {side} image is {img.shape[1]}x{img.shape[0]}, "
                    f"calibration expects {w}x{h}"
                )
        (m1l, m2l), (m1r, m2r) = self._maps
        return (
            cv2.remap(left, m1l, m2l, cv2.INTER_LINEAR),
            cv2.remap(right, m1r, m2r, cv2.INTER_LINEAR),
        )


class RectifiedSource(Source):
    """Wraps a source and rectifies every pair it reads; exposes the rectified rig."""

    def __init__(self, inner: Source, calib: StereoCalibration) -> None:
        super().__init__(calib.rig())
        self.inner = inner
        self.finite = inner.finite
        self.paced = inner.paced
        self.rectifier = Rectifier(calib)

    def open(self) -> None:
        self.inner.open()

    def read(self) -> Frames | None:
        frames = self.inner.read()
        if frames is None:
            return None
        try:
            frames.left, frames.right = self.rectifier.apply(frames.left, frames.right)
        except SourceError as exc:
            if self.finite:  # one odd file in a folder: skip it, the next pair may fit
                raise SkipPair("size", str(exc)) from None
            raise
        return frames

    def close(self) -> None:
        self.inner.close()
