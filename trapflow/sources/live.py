"""Two independently clocked cameras: a grab thread per camera, pairing by timestamp.

The threads only wait on the devices (I/O, GIL released); frames are matched by StereoSync,
unmatched ones dropped and counted. A camera that errors or stalls makes read() raise
SourceError with the reason, so capture can go inactive and retry with back-off.
source.options: tolerance_s (half a frame period), stall_s (2.0).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable

import numpy as np

from trapflow.calibration.camera import StereoRig
from trapflow.config.schema import SourceConfig
from trapflow.sources.base import Frames, Source, SourceError
from trapflow.sources.sync import StereoSync, default_tolerance_ns

log = logging.getLogger(__name__)

Grab = Callable[[], "np.ndarray | None"]
DEFAULT_STALL_S = 2.0
_QUEUE = 4


class CameraThread(threading.Thread):
    """Grabs frames from one camera into a small queue, newest kept; remembers why it stopped."""

    def __init__(self, name: str, grab: Grab) -> None:
        super().__init__(name=f"trapflow-grab-{name}", daemon=True)
        self.camera = name
        self.grab = grab
        self.frames: queue.Queue[tuple[int, np.ndarray]] = queue.Queue(maxsize=_QUEUE)
        self.error: str | None = None
        self.dropped = 0
        self._halt = threading.Event()

    def run(self) -> None:
        while not self._halt.is_set():
            try:
                img = self.grab()
            except Exception as exc:  # noqa: BLE001 - any driver failure ends this camera
                self.error = f"{self.camera}: {type(exc).__name__}: {exc}"
                return
            t = time.monotonic_ns()
            if img is None:
                self.error = f"{self.camera}: no frame (device gone or unplugged?)"
                return
            if self.frames.full():  # the consumer is slow: keep the newest frames
                try:
                    self.frames.get_nowait()
                    self.dropped += 1
                except queue.Empty:
                    pass
            self.frames.put((t, img))

    def halt(self) -> None:
        """Ask the loop to end after the current grab."""
        self._halt.set()


class LiveStereoSource(Source):
    """Base of camera sources; subclasses implement _open_camera(side, arg)."""

    paced = True
    finite = False
    kind = "live"

    def __init__(self, cfg: SourceConfig, rig: StereoRig, args: tuple[str, str]) -> None:
        super().__init__(rig)
        self.cfg = cfg
        self.args = args
        opts = cfg.options
        tol = opts.get("tolerance_s")
        tol_ns = int(float(tol) * 1e9) if tol is not None else default_tolerance_ns(cfg.rate_hz)
        self.sync: StereoSync[np.ndarray] = StereoSync(tol_ns)
        self.stall_ns = int(float(opts.get("stall_s", DEFAULT_STALL_S)) * 1e9)
        self._threads: list[CameraThread] = []
        self._releases: list[Callable[[], None]] = []

    def _open_camera(self, side: str, arg: str) -> tuple[Grab, Callable[[], None]]:
        raise NotImplementedError

    def open(self) -> None:
        self.close()
        try:
            for side, arg in zip(("left", "right"), self.args, strict=True):
                grab, release = self._open_camera(side, arg)
                self._releases.append(release)
                self._threads.append(CameraThread(f"{side} {arg}", grab))
        except SourceError:
            self.close()
            raise
        for t in self._threads:
            t.start()

    def read(self) -> Frames:
        if not self._threads:
            raise SourceError(f"{self.kind}: read() before open()")
        deadline = time.monotonic_ns() + self.stall_ns
        left_t, right_t = self._threads
        while True:
            pair = self.sync.pop()
            if pair is not None:
                tl, left, tr, right = pair
                return Frames(left=left, right=right, t_left_ns=tl, t_right_ns=tr)
            for th in self._threads:
                if th.error is not None and th.frames.empty():
                    raise SourceError(f"{self.kind}: camera {th.error}")
            for th, push in ((left_t, self.sync.push_left), (right_t, self.sync.push_right)):
                try:
                    t, img = th.frames.get(timeout=0.005)
                except queue.Empty:
                    continue
                push(t, img)
            # No *pair* for stall_s is a stall, even while the other camera keeps delivering.
            if time.monotonic_ns() > deadline:
                waiting = [th.camera for th in self._threads if th.frames.empty()]
                raise SourceError(f"{self.kind}: camera {', '.join(waiting) or 'pair'} stalled: "
                                  f"no pair for {self.stall_ns / 1e9:.1f} s")

    def close(self) -> None:
        for th in self._threads:
            th.halt()
        for release in self._releases:
            try:
                release()
            except Exception:
                log.debug("%s: release failed", self.kind, exc_info=True)
        for th in self._threads:
            th.join(timeout=2.0)
        self._threads = []
        self._releases = []
