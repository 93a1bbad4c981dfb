"""`v4l2:/dev/videoA,/dev/videoB` (or indices 0,1): two USB/CSI cameras through OpenCV."""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from trapflow.calibration.camera import StereoRig
from trapflow.config.schema import SourceConfig
from trapflow.sources.base import SourceError
from trapflow.sources.live import Grab, LiveStereoSource
from trapflow.sources.spec import split_pair


def opencv_grab(cap: cv2.VideoCapture) -> Grab:
    """A grab function reading one BGR frame from an opened capture."""

    def grab() -> np.ndarray | None:
        ok, img = cap.read()
        return img if ok else None

    return grab


class V4L2Source(LiveStereoSource):
    """Two V4L2 devices, each opened with the configured size and rate."""

    kind = "v4l2"

    def __init__(self, cfg: SourceConfig, rig: StereoRig) -> None:
        try:
            args = split_pair(cfg.uri)
        except ValueError as exc:
            raise SourceError(f"v4l2: {exc}") from None
        super().__init__(cfg, rig, args)

    def _open_camera(self, side: str, arg: str) -> tuple[Grab, Callable[[], None]]:
        device: int | str = int(arg) if arg.isdigit() else arg
        cap = cv2.VideoCapture(device, cv2.CAP_V4L2)
        if not cap.isOpened():
            cap.release()
            raise SourceError(f"v4l2: cannot open {side} camera {arg} "
                              "(missing, busy, or no permission on the device)")
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.cfg.width)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.cfg.height)
        cap.set(cv2.CAP_PROP_FPS, self.cfg.rate_hz)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # latest frame, not a stale queue
        got = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        if all(got) and got != self.rig.size:  # the driver chose another size: fail now
            cap.release()
            raise SourceError(
                f"v4l2: {side} camera {arg} gives {got[0]}x{got[1]}, but the rig is "
                f"{self.rig.width}x{self.rig.height}: give --size {got[0]}x{got[1]} "
                "(source.width/height) or a calibration for that size")
        return opencv_grab(cap), cap.release
