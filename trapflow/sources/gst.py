"""`gst:LEFT_PIPELINE,RIGHT_PIPELINE`: two GStreamer pipelines ending in appsink, via OpenCV."""

from __future__ import annotations

from collections.abc import Callable

import cv2

from trapflow.calibration.camera import StereoRig
from trapflow.config.schema import SourceConfig
from trapflow.sources.base import SourceError
from trapflow.sources.live import Grab, LiveStereoSource
from trapflow.sources.spec import split_gst
from trapflow.sources.v4l2 import opencv_grab


def opencv_has_gstreamer() -> bool:
    """Whether this OpenCV build can open GStreamer pipelines."""
    for line in cv2.getBuildInformation().splitlines():
        if line.strip().startswith("GStreamer:"):
            return "YES" in line.split(":", 1)[1]
    return False


class GstSource(LiveStereoSource):
    """Two pipelines, each delivering BGR frames to an appsink."""

    kind = "gst"

    def __init__(self, cfg: SourceConfig, rig: StereoRig) -> None:
        try:
            args = split_gst(cfg.uri)
        except ValueError as exc:
            raise SourceError(f"gst: {exc}") from None
        super().__init__(cfg, rig, args)

    def open(self) -> None:
        if not opencv_has_gstreamer():
            raise SourceError(
                "gst: this OpenCV was built without GStreamer (cv2.getBuildInformation() says "
                "'GStreamer: NO'); install an OpenCV built with it, e.g. the system python3-opencv "
                "package, instead of opencv-python-headless"
            )
        super().open()

    def _open_camera(self, side: str, arg: str) -> tuple[Grab, Callable[[], None]]:
        cap = cv2.VideoCapture(arg, cv2.CAP_GSTREAMER)
        if not cap.isOpened():
            cap.release()
            raise SourceError(f"gst: cannot start the {side} pipeline {arg!r}")
        return opencv_grab(cap), cap.release
