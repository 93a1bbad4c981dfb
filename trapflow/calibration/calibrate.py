"""Checkerboard stereo calibration with OpenCV: image pairs in, a StereoCalibration out.

Views where either side shows no complete board are rejected and named. Three models:
`pinhole` calibrates each camera (k1 k2 p1 p2) then the extrinsics with the intrinsics
fixed; `rational` is OpenCV's samples/cpp/stereo_calib.cpp step for step (one joint fit);
`fisheye` calibrates each equidistant lens, dropping views OpenCV finds ill-conditioned,
then the extrinsics. The rectification is computed by calibration.rectify.
"""

from __future__ import annotations

import glob
import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from trapflow.calibration.model import StereoCalibration, from_extrinsics
from trapflow.errors import TrapflowError

log = logging.getLogger(__name__)

MIN_VIEWS = 3
MODELS = ("pinhole", "rational", "fisheye")
_SUBPIX = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
# stereo_calib.cpp's own corner refinement and solver settings, for the `rational` model.
_SAMPLE_SUBPIX = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
_SAMPLE_SOLVER = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-5)
_SAMPLE_FLAGS = (cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_ZERO_TANGENT_DIST
                 | cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_SAME_FOCAL_LENGTH
                 | cv2.CALIB_RATIONAL_MODEL | cv2.CALIB_FIX_K3 | cv2.CALIB_FIX_K4
                 | cv2.CALIB_FIX_K5)
_FISHEYE_SOLVER = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-6)
_FISHEYE_FLAGS = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW | cv2.CALIB_CHECK_COND


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


def find_corners(path: Path, pattern: tuple[int, int], window: int = 5,
                 criteria: tuple[int, int, float] = _SUBPIX
                 ) -> tuple[np.ndarray | None, tuple[int, int]]:
    """Sub-pixel board corners in one image, or None; and the image size (w, h)."""
    gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if gray is None:
        raise CalibrationError(f"calibrate: cannot read image {path}")
    size = (gray.shape[1], gray.shape[0])
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, pattern, flags=flags)
    if not found:
        return None, size
    return cv2.cornerSubPix(gray, corners, (window, window), (-1, -1), criteria), size


def same_order(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """The right corners in the left's order: a board with an even side has two valid
    corner orders, and OpenCV may pick a different one in each eye (a wrong view that
    breaks the extrinsics). Side by side cameras see the board's first-to-last diagonal
    pointing the same way."""
    a = left.reshape(-1, 2)
    b = right.reshape(-1, 2)
    if float(np.dot(a[-1] - a[0], b[-1] - b[0])) < 0:
        return np.ascontiguousarray(right[::-1])
    return right


def board_points(pattern: tuple[int, int], square_m: float) -> np.ndarray:
    """The board's inner corners in its own plane (z = 0), metres, in OpenCV's corner order."""
    cols, rows = pattern
    grid = np.zeros((rows * cols, 3), np.float32)
    grid[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_m
    return grid


def calibrate_stereo(left: list[Path], right: list[Path], pattern: tuple[int, int],
                     square_m: float, model: str = "pinhole") -> CalibrationReport:
    """Calibrate from paired image lists (the i-th left with the i-th right)."""
    if model not in MODELS:
        raise CalibrationError(f"calibrate: model: expected one of {', '.join(MODELS)}, "
                               f"got {model!r}")
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
    window, criteria = (11, _SAMPLE_SUBPIX) if model == "rational" else (5, _SUBPIX)
    for lp, rp in zip(left, right, strict=True):
        cl, sl = find_corners(lp, pattern, window, criteria)
        cr, sr = find_corners(rp, pattern, window, criteria)
        if sl != sr or (size is not None and sl != size):
            raise CalibrationError(f"calibrate: {lp.name} is {sl}, {rp.name} is {sr}; "
                                   f"expected all images {size or sl}")
        size = sl
        if cl is None or cr is None:
            rejected.append(f"{lp.name}|{rp.name}")
            continue
        pts_l.append(cl)
        pts_r.append(same_order(cl, cr))
        used.append(f"{lp.name}|{rp.name}")
    assert size is not None
    if len(used) < MIN_VIEWS:
        raise CalibrationError(
            f"calibrate: board {pattern[0]}x{pattern[1]} (inner corners) found in both images of "
            f"{len(used)} of {len(left)} pairs; expected at least {MIN_VIEWS}"
        )
    try:
        if model == "fisheye":
            fit = _fit_fisheye(obj, pts_l, pts_r, size, used, rejected)
        else:
            fit = _fit_pinhole(obj, pts_l, pts_r, size, joint=model == "rational")
    except cv2.error as exc:
        raise CalibrationError(f"calibrate: OpenCV could not fit the {model} model to "
                               f"{len(used)} views: {str(exc).strip()[-200:]}") from None
    rms, k1, d1, k2, d2, r, t, e, f = fit
    calib = from_extrinsics(
        model="fisheye" if model == "fisheye" else "pinhole", size=size,
        k1=k1, d1=d1, k2=k2, d2=d2, r=r, t=t,
        E=None if e is None else _m(e), F=None if f is None else _m(f),
        rms_px=float(rms), views_used=len(used), views_rejected=rejected,
        pattern=pattern, square_m=square_m,
    )
    log.info("calibrate: %s model, rms %.3f px over %d views, %d rejected, baseline %.4f m",
             model, rms, len(used), len(rejected), calib.baseline_m)
    return CalibrationReport(calibration=calib, rms_px=float(rms), used=used, rejected=rejected)


Fit = tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
            np.ndarray | None, np.ndarray | None]


def _m(a: np.ndarray) -> list[list[float]]:
    rows = np.asarray(a, np.float64)
    return [[float(v) for v in row] for row in rows.reshape(rows.shape[0], -1)]


def _fit_pinhole(obj: np.ndarray, pts_l: list[np.ndarray], pts_r: list[np.ndarray],
                 size: tuple[int, int], joint: bool) -> Fit:
    objs = [obj] * len(pts_l)
    if joint:
        # stereo_calib.cpp: initial K from the views, then one joint fit of everything.
        k1 = cv2.initCameraMatrix2D(objs, pts_l, size, 0)
        k2 = cv2.initCameraMatrix2D(objs, pts_r, size, 0)
        rms, k1, d1, k2, d2, r, t, e, f = cv2.stereoCalibrate(
            objs, pts_l, pts_r, k1, np.zeros(14), k2, np.zeros(14), size, flags=_SAMPLE_FLAGS,
            criteria=_SAMPLE_SOLVER)
        return float(rms), k1, d1, k2, d2, r, t, e, f
    # k3 is left at 0: with boards that rarely reach the corners it overfits and wrecks
    # the rectified focal length (alpha=0 then zooms in on a wildly curved border).
    flags = cv2.CALIB_FIX_K3
    _, k1, d1, _, _ = cv2.calibrateCamera(objs, pts_l, size, None, None, flags=flags)
    _, k2, d2, _, _ = cv2.calibrateCamera(objs, pts_r, size, None, None, flags=flags)
    rms, k1, d1, k2, d2, r, t, e, f = cv2.stereoCalibrate(
        objs, pts_l, pts_r, k1, d1, k2, d2, size, flags=cv2.CALIB_FIX_INTRINSIC,
        criteria=_SUBPIX)
    return float(rms), k1, d1, k2, d2, r, t, e, f


def _fit_fisheye(obj: np.ndarray, pts_l: list[np.ndarray], pts_r: list[np.ndarray],
                 size: tuple[int, int], used: list[str], rejected: list[str]) -> Fit:
    """Each lens, then the extrinsics; views OpenCV cannot use move from used to rejected."""
    obj64 = obj.reshape(1, -1, 3).astype(np.float64)
    sides = [[p.reshape(1, -1, 2).astype(np.float64) for p in pts] for pts in (pts_l, pts_r)]
    while True:
        if len(used) < MIN_VIEWS:
            raise CalibrationError(f"calibrate: {len(used)} views left after dropping the "
                                   f"ill-conditioned ones; expected at least {MIN_VIEWS}")
        bad = None
        lenses = []
        for pts in sides:
            try:
                rms, k, d, _, _ = cv2.fisheye.calibrate(
                    [obj64] * len(pts), pts, size, np.eye(3), np.zeros(4),
                    flags=_FISHEYE_FLAGS, criteria=_FISHEYE_SOLVER)
            except cv2.error as exc:
                bad = _bad_view(str(exc), obj64, pts, size)
                break
            lenses.append((k, d))
        if bad is None:
            break
        log.info("calibrate: view %s dropped: OpenCV finds it ill-conditioned", used[bad])
        rejected.append(used.pop(bad))
        for pts in sides:
            pts.pop(bad)
    (k1, d1), (k2, d2) = lenses
    n = len(used)
    rms, k1, d1, k2, d2, r, t = cv2.fisheye.stereoCalibrate(
        [obj64] * n, sides[0], sides[1], k1, d1, k2, d2, size,
        flags=cv2.CALIB_FIX_INTRINSIC, criteria=_FISHEYE_SOLVER)[:7]
    return float(rms), k1, d1, k2, d2, r, t, None, None


def _bad_view(message: str, obj: np.ndarray, pts: list[np.ndarray],
              size: tuple[int, int]) -> int:
    """The view an OpenCV fisheye error is about: named in CALIB_CHECK_COND's message, or
    (for errors of the initial guess, which name none) the first that fails on its own."""
    found = re.search(r"input array (\d+)", message)
    if found:
        return int(found.group(1))
    one_step = (cv2.TERM_CRITERIA_COUNT, 1, 0.0)
    for i, view in enumerate(pts):
        try:
            cv2.fisheye.calibrate([obj], [view], size, np.eye(3), np.zeros(4),
                                  flags=_FISHEYE_FLAGS, criteria=one_step)
        except cv2.error:
            return i
    raise CalibrationError(f"calibrate: the fisheye fit fails and no single view is the "
                           f"cause: {message.strip()[-200:]}")
