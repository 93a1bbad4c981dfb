"""Checkerboard stereo calibration with OpenCV: image pairs in, a StereoCalibration out.

Views where either side shows no complete board are rejected and named; intrinsics are
calibrated per camera first, then the extrinsics with the intrinsics fixed, then rectified.
"""

from __future__ import annotations

import glob
import logging
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from trapflow.calibration import StereoCalibration
from trapflow.errors import TrapflowError

log = logging.getLogger(__name__)

MIN_VIEWS = 3
_SUBPIX = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)


class CalibrationError(TrapflowError):
    """Calibration cannot run: no images, unpaired globs, too few boards detected."""


@dataclass
class CalibrationReport:
    """The result and what was left out."""

    calibration: StereoCalibration
    rms_px: float
    used: list[str] = field(default_factory=list)
    rejected: list[str] = field(default_factory=list)


def parse_pattern(text: str) -> tuple[int, int]:
    """`9x6` (inner corners per row x per column) -> (9, 6); ValueError says what was expected."""
    cols, sep, rows = text.lower().partition("x")
    if not sep or not cols.isdigit() or not rows.isdigit() or int(cols) < 2 or int(rows) < 2:
        raise ValueError(f"expected COLSxROWS inner corners like 9x6, got {text!r}")
    return int(cols), int(rows)


def expand(pattern_glob: str) -> list[Path]:
    """Sorted files matching a glob (or the one file named)."""
    return [Path(p) for p in sorted(glob.glob(pattern_glob))]


def find_corners(path: Path, pattern: tuple[int, int]) -> tuple[np.ndarray | None, tuple[int, int]]:
    """Sub-pixel board corners in one image, or None; and the image size (w, h)."""
    gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if gray is None:
        raise CalibrationError(f"calibrate: cannot read image {path}")
    size = (gray.shape[1], gray.shape[0])
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, pattern, flags=flags)
    if not found:
        return None, size
    return cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), _SUBPIX), size


def board_points(pattern: tuple[int, int], square_m: float) -> np.ndarray:
    """The board's inner corners in its own plane (z = 0), metres, in OpenCV's corner order."""
    cols, rows = pattern
    grid = np.zeros((rows * cols, 3), np.float32)
    grid[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_m
    return grid


def calibrate_stereo(left: list[Path], right: list[Path], pattern: tuple[int, int],
                     square_m: float) -> CalibrationReport:
    """Calibrate from paired image lists (the i-th left with the i-th right)."""
    if not left or not right:
        raise CalibrationError(f"calibrate: no images ({len(left)} left, {len(right)} right)")
    if len(left) != len(right):
        raise CalibrationError(f"calibrate: {len(left)} left and {len(right)} right images; "
                               "expected the same number, paired in sorted order")
    obj = board_points(pattern, square_m)
    pts_l: list[np.ndarray] = []
    pts_r: list[np.ndarray] = []
    used: list[str] = []
    rejected: list[str] = []
    size: tuple[int, int] | None = None
    for lp, rp in zip(left, right, strict=True):
        cl, sl = find_corners(lp, pattern)
        cr, sr = find_corners(rp, pattern)
        if sl != sr or (size is not None and sl != size):
            raise CalibrationError(f"calibrate: {lp.name} is {sl}, {rp.name} is {sr}; "
                                   f"expected all images {size or sl}")
        size = sl
        if cl is None or cr is None:
            rejected.append(f"{lp.name}|{rp.name}")
            continue
        pts_l.append(cl)
        pts_r.append(cr)
        used.append(f"{lp.name}|{rp.name}")
    assert size is not None
    if len(used) < MIN_VIEWS:
        raise CalibrationError(
            f"calibrate: board {pattern[0]}x{pattern[1]} (inner corners) found in both images of "
            f"{len(used)} of {len(left)} pairs; expected at least {MIN_VIEWS}"
        )
    objs = [obj] * len(used)
    # k3 is left at 0: with boards that rarely reach the corners it overfits and wrecks
    # the rectified focal length (alpha=0 then zooms in on a wildly curved border).
    flags = cv2.CALIB_FIX_K3
    _, k1, d1, _, _ = cv2.calibrateCamera(objs, pts_l, size, None, None, flags=flags)
    _, k2, d2, _, _ = cv2.calibrateCamera(objs, pts_r, size, None, None, flags=flags)
    rms, k1, d1, k2, d2, r, t, e, f = cv2.stereoCalibrate(
        objs, pts_l, pts_r, k1, d1, k2, d2, size, flags=cv2.CALIB_FIX_INTRINSIC, criteria=_SUBPIX
    )
    r1, r2, p1, p2, q, _, _ = cv2.stereoRectify(k1, d1, k2, d2, size, r, t,
                                                flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)

    def m(a: np.ndarray) -> list[list[float]]:
        rows = np.asarray(a, np.float64).reshape(a.shape[0], -1)
        return [[float(v) for v in row] for row in rows]

    calib = StereoCalibration(
        image_width=size[0], image_height=size[1],
        K1=m(k1), D1=[float(v) for v in d1.ravel()], K2=m(k2), D2=[float(v) for v in d2.ravel()],
        R=m(r), T=[float(v) for v in t.ravel()], E=m(e), F=m(f),
        R1=m(r1), R2=m(r2), P1=m(p1), P2=m(p2), Q=m(q),
        baseline_m=float(np.linalg.norm(t)), rms_px=float(rms), views_used=len(used),
        views_rejected=rejected, pattern=pattern, square_m=square_m,
    )
    log.info("calibrate: rms %.3f px over %d views, %d rejected, baseline %.4f m",
             rms, len(used), len(rejected), calib.baseline_m)
    return CalibrationReport(calibration=calib, rms_px=float(rms), used=used, rejected=rejected)
