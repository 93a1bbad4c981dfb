"""Live camera sources: grab threads + timestamp pairing with scripted cameras, and the
one-line errors of devices that are missing, unsupported or not installed."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np
import pytest

from trapflow.calibration.camera import StereoRig
from trapflow.config.schema import SourceConfig
from trapflow.sources.base import SourceError
from trapflow.sources.factory import open_source
from trapflow.sources.gst import opencv_has_gstreamer
from trapflow.sources.live import Grab, LiveStereoSource

RIG = StereoRig.from_fov(32, 24, 70.0, 0.12)


class ScriptedCameras(LiveStereoSource):
    """Cameras that deliver frames at a given period (a Condition-timed wait, like a driver)."""

    kind = "scripted"

    def __init__(self, period_s: float, fail_right_after: int = -1, stall_right_after: int = -1,
                 **options: float) -> None:
        cfg = SourceConfig(kind="synthetic", rate_hz=1 / period_s, options=dict(options))
        super().__init__(cfg, RIG, ("0", "1"))
        self.period_s = period_s
        self.fail_right_after = fail_right_after
        self.stall_right_after = stall_right_after
        self.released: list[str] = []
        self._gone = threading.Event()

    def _open_camera(self, side: str, arg: str) -> tuple[Grab, Callable[[], None]]:
        count = [0]

        def grab() -> np.ndarray | None:
            n = count[0]
            count[0] += 1
            if side == "right" and n == self.fail_right_after:
                return None
            if side == "right" and self.stall_right_after >= 0 and n >= self.stall_right_after:
                self._gone.wait(5.0)  # a hung driver: blocks until released
                return None
            self._gone.wait(self.period_s)
            return np.full((24, 32, 3), n % 256, np.uint8)

        def release() -> None:
            self.released.append(side)
            self._gone.set()

        return grab, release


@pytest.mark.timeout(20)
def test_pairs_two_free_running_cameras() -> None:
    src = ScriptedCameras(period_s=0.02)
    src.open()
    try:
        got = [src.read() for _ in range(10)]
    finally:
        src.close()
    assert sorted(src.released) == ["left", "right"]
    assert all(abs(f.t_left_ns - f.t_right_ns) <= src.sync.tolerance_ns for f in got)
    assert all(b.t_left_ns > a.t_left_ns for a, b in zip(got[:-1], got[1:], strict=True))
    assert src.sync.stats.pairs == 10
    assert src.sync.stats.skew_max_ns <= src.sync.tolerance_ns


@pytest.mark.timeout(20)
def test_camera_that_disappears_raises_with_reason() -> None:
    src = ScriptedCameras(period_s=0.01, fail_right_after=3)
    src.open()
    try:
        with pytest.raises(SourceError, match="camera right 1: no frame"):
            for _ in range(50):
                src.read()
    finally:
        src.close()


@pytest.mark.timeout(20)
def test_camera_that_stalls_raises_after_stall_time() -> None:
    src = ScriptedCameras(period_s=0.01, stall_right_after=2, stall_s=0.3)
    src.open()
    t0 = time.monotonic()
    try:
        with pytest.raises(SourceError, match="stalled: no pair for 0.3 s"):
            for _ in range(50):
                src.read()
    finally:
        src.close()
    assert time.monotonic() - t0 < 5


def make(kind: str, uri: str) -> LiveStereoSource:
    src = open_source(SourceConfig(kind=kind, uri=uri), RIG)
    assert isinstance(src, LiveStereoSource)
    return src


def test_v4l2_missing_device_is_one_clear_error(tmp_path: object) -> None:
    src = make("v4l2", "/dev/video-missing-a,/dev/video-missing-b")
    with pytest.raises(SourceError, match="v4l2: cannot open left camera /dev/video-missing-a"):
        src.open()
    src.close()


@pytest.mark.skipif(opencv_has_gstreamer(), reason="this OpenCV has GStreamer")
def test_gst_without_gstreamer_says_so() -> None:
    src = make("gst", "videotestsrc ! appsink,videotestsrc ! appsink")
    with pytest.raises(SourceError, match="built without GStreamer"):
        src.open()


def test_picamera2_missing_says_what_to_install() -> None:
    pytest.importorskip("cv2")
    try:
        import picamera2  # noqa: F401
    except ImportError:
        src = make("picamera2", "0,1")
        with pytest.raises(SourceError, match="sudo apt install python3-picamera2"):
            src.open()
    else:
        pytest.skip("picamera2 is installed here")
