"""Video file sources: two files (left, right) or one side-by-side file, paired by frame index."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import cv2
import numpy as np

from trapflow.calibration.camera import StereoRig
from trapflow.config.schema import SourceConfig
from trapflow.sources.base import Frames, Geometry, Source, SourceError
from trapflow.sources.decode import same_size
from trapflow.sources.spec import split_pair

log = logging.getLogger(__name__)


def open_video(path: Path) -> cv2.VideoCapture:
    """An opened capture for a file, or SourceError saying why not."""
    if not path.is_file():
        raise SourceError(f"video: file not found: {path}")
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        cap.release()
        raise SourceError(f"video: cannot decode {path} (not a video, or no codec for it)")
    return cap


class VideoSource(Source):
    """`video:LEFT,RIGHT` or `video:SIDE_BY_SIDE`; frame i of left pairs with frame i of right."""

    finite = True

    def __init__(self, cfg: SourceConfig, rig: StereoRig) -> None:
        super().__init__(rig)
        self.cfg = cfg
        self.loop = cfg.loop
        self.finite = not cfg.loop
        if "," in cfg.uri:
            left, right = split_pair(cfg.uri)
            self.paths: tuple[Path, ...] = (Path(left), Path(right))
        else:
            self.paths = (Path(cfg.uri),)
        self._caps: list[cv2.VideoCapture] = []
        self._index = 0  # frames delivered, across loops: the time base
        self._period_ns = int(1e9 / cfg.rate_hz)
        self._t0 = 0

    def geometry(self) -> Geometry:
        """The first frame's size (half of it across for a side-by-side file)."""
        cap = open_video(self.paths[0])
        try:
            ok, img = cap.read()
        finally:
            cap.release()
        if not ok or img is None:
            raise SourceError(f"video: no frame could be decoded from {self.paths[0]}")
        h, w = img.shape[:2]
        return Geometry(size=(w if len(self.paths) > 1 else w // 2, h),
                        where=f"video {self.cfg.uri}")

    def open(self) -> None:
        self._caps = [open_video(p) for p in self.paths]
        fps = self._caps[0].get(cv2.CAP_PROP_FPS)
        if fps and 0 < fps <= 1000:
            self._period_ns = int(1e9 / fps)
        self._t0 = time.monotonic_ns()

    def _grab(self) -> list[np.ndarray] | None:
        images = []
        for cap in self._caps:
            ok, img = cap.read()
            if not ok or img is None:
                return None
            images.append(img)
        return images

    def read(self) -> Frames | None:
        if not self._caps:
            raise SourceError("video: read() before open()")
        images = self._grab()
        if images is None and self.loop and self._index > 0:
            for cap in self._caps:
                cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
            images = self._grab()
        if images is None:
            if self._index == 0:
                raise SourceError(f"video: no frame could be decoded from {self.paths[0]}")
            return None
        if len(images) == 1:
            img = images[0]
            half = img.shape[1] // 2
            if half == 0:
                raise SourceError(f"video: side-by-side frame too narrow ({img.shape[1]} px)")
            left, right = img[:, :half], img[:, half : 2 * half]
        else:
            left, right = images
        t = self._t0 + self._index * self._period_ns
        self._index += 1
        if len(images) == 2:  # a frame pair of two sizes is skipped; the files go on
            same_size(left, right, f"video: frame {self._index - 1}")
        return Frames(left=np.ascontiguousarray(left), right=np.ascontiguousarray(right),
                      t_left_ns=t, t_right_ns=t)

    def close(self) -> None:
        for cap in self._caps:
            cap.release()
        self._caps = []
