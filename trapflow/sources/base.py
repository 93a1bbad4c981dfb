"""The source interface: something that yields time-stamped stereo frames."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trapflow.calibration.camera import StereoRig
from trapflow.errors import TrapflowError
from trapflow.wire.messages import Truth


class SourceError(TrapflowError):
    """A source cannot open or stopped delivering frames (camera gone, file unreadable)."""


class SkipPair(SourceError):
    """One pair of a finite source cannot be read; the source has moved past it and goes on.

    `kind` is a short class of the fault for the ledger (unreadable, truncated, size,
    undecodable); the message names the file or message index, for a log line of its own.
    """

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


@dataclass
class Frames:
    """One stereo capture: BGR uint8 images and their monotonic capture times.

    `t_wall_ns` is the source's own wall-clock capture time, where it has one (a recording's
    stamps): results are labelled with it. None (a camera, files): the clock at capture.
    """

    left: np.ndarray
    right: np.ndarray
    t_left_ns: int
    t_right_ns: int
    truth: Truth | None = None  # only synthetic sources know it; seq is filled by capture
    t_wall_ns: int | None = None

    def right_minus_left_ns(self) -> int:
        """Capture-time skew between the two cameras."""
        return self.t_right_ns - self.t_left_ns


@dataclass(frozen=True)
class Geometry:
    """What a source knows of its own geometry before it is opened (sources.rig decides)."""

    size: tuple[int, int] | None = None  # (width, height) of its real frames
    rig: StereoRig | None = None  # its own calibration: KITTI calib.txt, CameraInfo
    origin: str = ""  # where the rig came from, e.g. "calib.txt in DIR"
    where: str = ""  # what the frames are, for messages: "images in DIR"
    # The side of the AprilTags the source lays (a synthetic world knows it); None where the
    # source cannot know (a camera): the tags pool's params then say it.
    tag_size_m: float | None = None


class Source:
    """Base of every source. Capture calls open(), then read() at its rate, then close()."""

    #: a finite source (file, folder, recording) ends the run when read() returns None
    finite: bool = False
    #: live sources pace themselves (read() blocks); others are paced by capture's rate
    paced: bool = False

    def __init__(self, rig: StereoRig) -> None:
        self.rig = rig

    def geometry(self) -> Geometry:
        """Its frame size and own calibration where it can tell without being opened
        (a file's first frame, a calib.txt, CameraInfo); a live camera tells nothing."""
        return Geometry()

    def open(self) -> None:
        """Acquire the device or file; raise SourceError with a reason."""

    def read(self) -> Frames | None:
        """The next pair, or None when a finite source is exhausted."""
        raise NotImplementedError

    def close(self) -> None:
        """Release the device or file."""
