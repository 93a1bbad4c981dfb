"""`picamera2:0,1`: the two Camera Modules of a Raspberry Pi through Picamera2 (optional)."""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

import numpy as np

from trapflow.calibration.camera import StereoRig
from trapflow.config.schema import SourceConfig
from trapflow.sources.base import SourceError
from trapflow.sources.live import Grab, LiveStereoSource
from trapflow.sources.spec import split_pair

INSTALL_HINT = ("the picamera2 package is not installed; on Raspberry Pi OS: "
                "sudo apt install python3-picamera2 (and create the venv with "
                "--system-site-packages)")


def load_picamera2() -> Any:
    """The Picamera2 class, or SourceError saying what to install."""
    try:
        return importlib.import_module("picamera2").Picamera2
    except ImportError:
        raise SourceError(f"picamera2: {INSTALL_HINT}") from None


class Picamera2Source(LiveStereoSource):
    """Two cameras by number, each configured for the source size in BGR."""

    kind = "picamera2"

    def __init__(self, cfg: SourceConfig, rig: StereoRig) -> None:
        try:
            args = split_pair(cfg.uri)
        except ValueError as exc:
            raise SourceError(f"picamera2: {exc}") from None
        super().__init__(cfg, rig, args)

    def _open_camera(self, side: str, arg: str) -> tuple[Grab, Callable[[], None]]:
        cls = load_picamera2()
        try:
            cam = cls(camera_num=int(arg))
            # "RGB888" in libcamera terms is B, G, R in memory: what OpenCV calls BGR.
            config = cam.create_video_configuration(
                main={"size": (self.cfg.width, self.cfg.height), "format": "RGB888"},
                controls={"FrameRate": self.cfg.rate_hz},
            )
            cam.configure(config)
            cam.start()
        except Exception as exc:  # noqa: BLE001 - libcamera raises assorted errors
            raise SourceError(f"picamera2: cannot open {side} camera {arg}: {exc}") from None

        def grab() -> np.ndarray | None:
            return np.ascontiguousarray(cam.capture_array("main")[:, :, :3])

        def release() -> None:
            cam.stop()
            cam.close()

        return grab, release
