"""The field check of a calibration: a checkerboard's edges and diagonals, or the distance
between two points, triangulated from a raw (unrectified) pair against what they should be.

Pure: a StereoCalibration and images in, lengths and their errors out; field_board and
field_points also judge them (trapflow.measure.verdict) and give no number that cannot be
right.
"""

from __future__ import annotations

import math

import cv2
import msgspec
import numpy as np

from trapflow.calibration.calibrate import same_order
from trapflow.calibration.model import StereoCalibration
from trapflow.errors import TrapflowError
from trapflow.measure.stereo import MeasureParams, Unmeasured, match_ncc, triangulate
from trapflow.measure.verdict import (
    POINT_SD_PX,
    Reason,
    judge_geometry,
    judge_inputs,
    judge_sizes,
)
from trapflow.sources.rectify import Rectifier

_SUBPIX = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
# Corners refined as trapflow calibrate refines them (calibrate.find_corners: half-size 5,
# an 11 x 11 window), so the check measures the points the calibration was fitted to. A
# 23 x 23 window (half-size 11) reached past the kit's smallest squares (22 px) and moved end
# corners of a row by 2.5 to 6.4 px: pairs 01 and 02 of the very set the rig was calibrated
# on failed with diagonals -2.5 % and +1.9 %; with 11 x 11 all 13 pairs pass (within 0.7 %).
SUBPIX_WINDOW = 5
MATCH_HALF_PX = 12  # a point's matching patch: 25 x 25 pixels around it
# The field check's pass marks: issue 24's targets on OpenCV's sample set (30 mm squares:
# 1.5 mm RMS on edges, 1 % on the 283 mm diagonals), edges as a share of the square so that
# other boards are judged alike. Rows of matched corners more than a pixel apart after
# rectification: the calibration no longer fits the rig (a camera moved in its housing).
EDGE_RMS_PCT = 5.0
DIAGONAL_PCT = 1.0
RECTIFIED_DY_PX = 1.0


class MeasureError(TrapflowError):
    """A measurement cannot be made: no board in an image, a point with no match."""


class BoardCheck(msgspec.Struct, frozen=True, kw_only=True):
    """A checkerboard measured in 3-D against its known geometry (lengths in metres)."""

    pattern: tuple[int, int]
    square_m: float
    edges_m: list[float]  # every adjacent-corner distance: rows first, then columns
    edge_rms_mm: float  # RMS of (edge - square)
    edge_max_mm: float  # largest |edge - square|
    diagonals_m: tuple[float, float]  # first to last corner, and the other diagonal
    diagonal_m: float  # what each diagonal should be
    diagonal_err_pct: tuple[float, float]
    rectified_dy_px: float  # RMS row difference of matched corners: 0 for a sound calibration
    disparities_px: tuple[float, float]  # the corners' smallest and largest (rectified)


class PointDistance(msgspec.Struct, frozen=True, kw_only=True):
    """Two points triangulated (rectified left camera frame, metres) and their distance."""

    a: tuple[float, float, float]
    b: tuple[float, float, float]
    distance_m: float
    distance_sd_m: float
    disparities_px: tuple[float, float]


def rectify_points(calib: StereoCalibration, pts: np.ndarray, right: bool = False
                   ) -> np.ndarray:
    """Raw-image pixels (N, 2) to rectified pixels: undistorted, rotated by R1 (R2), then
    projected by P1 (P2), as the calibration's rectification maps images."""
    k, d, r, p = ("K2", "D2", "R2", "P2") if right else ("K1", "D1", "R1", "P1")
    src = np.asarray(pts, np.float64).reshape(-1, 1, 2)
    if calib.model == "fisheye":
        out = cv2.fisheye.undistortPoints(src, calib.arr(k), calib.arr(d).reshape(4, 1),
                                          R=calib.arr(r), P=calib.arr(p))
    else:
        out = cv2.undistortPoints(src, calib.arr(k), calib.arr(d), R=calib.arr(r),
                                  P=calib.arr(p))
    return np.asarray(out, np.float64).reshape(-1, 2)


def triangulate_rectified(calib: StereoCalibration, left: np.ndarray, right: np.ndarray
                          ) -> np.ndarray:
    """(N, 3) points from rectified left and right pixels: disparity along x, the row of
    the mean of both eyes (they differ by the calibration's residual only)."""
    rig = calib.rig()
    out = [triangulate(rig, float(a[0]), float((a[1] + b[1]) / 2.0), float(a[0] - b[0]))
           for a, b in zip(left, right, strict=True)]
    return np.array(out).reshape(-1, 3)


def find_board(gray: np.ndarray, pattern: tuple[int, int]) -> np.ndarray | None:
    """Sub-pixel inner corners (N, 2) of a board in one grey image, OpenCV's order; or None."""
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, pattern, flags=flags)
    if not found:
        return None
    refined = cv2.cornerSubPix(gray, corners, (SUBPIX_WINDOW, SUBPIX_WINDOW), (-1, -1),
                               _SUBPIX)
    return np.asarray(refined, np.float64).reshape(-1, 2)


def board_corners(left: np.ndarray, right: np.ndarray, pattern: tuple[int, int]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The board's corners in both raw grey images, the right in the left's order."""
    cl = find_board(left, pattern)
    cr = find_board(right, pattern)
    for side, c in (("left", cl), ("right", cr)):
        if c is None:
            raise MeasureError(f"board {pattern[0]}x{pattern[1]} (inner corners): expected "
                               f"it in the {side} image, found none")
    assert cl is not None and cr is not None
    return cl, same_order(cl, cr).reshape(-1, 2)


def board_edges(points: np.ndarray, pattern: tuple[int, int]) -> np.ndarray:
    """Distances between adjacent corners: along each row, then along each column."""
    cols, rows = pattern
    grid = points.reshape(rows, cols, -1)
    along = np.linalg.norm(np.diff(grid, axis=1), axis=2).ravel()
    down = np.linalg.norm(np.diff(grid, axis=0), axis=2).ravel()
    out: np.ndarray = np.concatenate([along, down])
    return out


def check_board(calib: StereoCalibration, left: np.ndarray, right: np.ndarray,
                pattern: tuple[int, int], square_m: float) -> BoardCheck:
    """Every edge and both diagonals of a board in a raw pair against its known squares."""
    gl, gr = _grey(left), _grey(right)
    cl, cr = board_corners(gl, gr, pattern)
    rl, rr = rectify_points(calib, cl), rectify_points(calib, cr, right=True)
    pts = triangulate_rectified(calib, rl, rr)
    edges = board_edges(pts, pattern)
    err = edges - square_m
    cols, rows = pattern
    diag = square_m * math.hypot(cols - 1, rows - 1)
    d1 = float(np.linalg.norm(pts[0] - pts[-1]))
    d2 = float(np.linalg.norm(pts[cols - 1] - pts[(rows - 1) * cols]))
    return BoardCheck(
        pattern=pattern, square_m=square_m, edges_m=[round(float(e), 6) for e in edges],
        edge_rms_mm=round(1000 * float(np.sqrt(np.mean(err * err))), 4),
        edge_max_mm=round(1000 * float(np.abs(err).max()), 4),
        diagonals_m=(round(d1, 6), round(d2, 6)), diagonal_m=round(diag, 6),
        diagonal_err_pct=(round(100 * (d1 - diag) / diag, 4), round(100 * (d2 - diag) / diag, 4)),
        rectified_dy_px=round(float(np.sqrt(np.mean((rl[:, 1] - rr[:, 1]) ** 2))), 4),
        disparities_px=(round(float((rl[:, 0] - rr[:, 0]).min()), 3),
                        round(float((rl[:, 0] - rr[:, 0]).max()), 3)),
    )


PASS_TEXT = (f"edges within {EDGE_RMS_PCT:g} % RMS, diagonals within {DIAGONAL_PCT:g} %, "
             f"rows within {RECTIFIED_DY_PX:g} px")


def board_reasons(check: BoardCheck) -> list[Reason]:
    """Every pass mark the board misses (none: the rig still measures right)."""
    out = []
    edge_pct = 100 * check.edge_rms_mm / (1000 * check.square_m)
    diag = max(abs(e) for e in check.diagonal_err_pct)
    if check.disparities_px[0] <= 0:
        lo, hi = check.disparities_px
        out.append(Reason(kind="swapped", subject="board", message=(
            f"corners at disparities {lo:.1f} to {hi:.1f} px after rectification: a board "
            "in front of the rig has every disparity positive; LEFT and RIGHT look swapped "
            "(give the left camera's frame first)")))
    if edge_pct > EDGE_RMS_PCT:
        out.append(Reason(kind="edges", subject="board", message=(
            f"edges off by {check.edge_rms_mm:.2f} mm RMS ({edge_pct:.1f} % of the square, "
            f"limit {EDGE_RMS_PCT:g} %)")))
    if diag > DIAGONAL_PCT:
        out.append(Reason(kind="diagonal", subject="board", message=(
            f"a diagonal off by {diag:.2f} % (limit {DIAGONAL_PCT:g} %)")))
    if check.rectified_dy_px > RECTIFIED_DY_PX:
        out.append(Reason(kind="rows", subject="board", message=(
            f"matched corners {check.rectified_dy_px:.2f} px apart in rows after "
            f"rectification (limit {RECTIFIED_DY_PX:g} px): the calibration no longer fits "
            "the rig")))
    return out


def field_board(calib: StereoCalibration, left: np.ndarray, right: np.ndarray,
                pattern: tuple[int, int], square_m: float
                ) -> tuple[list[Reason], BoardCheck | None]:
    """The board check of `trapflow measure --board`: the images' sizes judged, the board
    measured and judged against the pass marks (the check is kept when it fails them)."""
    reasons = judge_sizes(calib.size, _sizes(left, right))
    if reasons:
        return reasons, None
    try:
        check = check_board(calib, left, right, pattern, square_m)
    except MeasureError as exc:
        return [Reason(kind="no_board", subject="--board", message=(
            f"{exc}; give the board's inner corners (--board 9x6 for 10 x 7 squares) with "
            "the whole board in both images"))], None
    return board_reasons(check), check


def field_points(calib: StereoCalibration, left: np.ndarray, right: np.ndarray,
                 pts_left: np.ndarray, pts_right: np.ndarray | None = None,
                 params: MeasureParams | None = None
                 ) -> tuple[list[Reason], PointDistance | None]:
    """The scale bar of `trapflow measure --points`: judged before measuring (sizes, points
    inside, two points, matches on their rows and in front), measured, and a match found by
    correlation judged again; a distance only where no reason stands against it."""
    a = [(float(x), float(y)) for x, y in np.asarray(pts_left, np.float64).reshape(-1, 2)]
    b = None if pts_right is None else [
        (float(x), float(y)) for x, y in np.asarray(pts_right, np.float64).reshape(-1, 2)]
    reasons = judge_inputs(calib.size, _sizes(left, right), a, b)
    if reasons:
        return reasons, None
    rl = rectify_points(calib, np.array(a))
    if b is not None:
        reasons = judge_geometry(_pixels(rl), _pixels(rectify_points(calib, np.array(b), True)),
                                 calib.rms_px)
        if reasons:
            return reasons, None
    try:
        got = measure_points(calib, left, right, np.array(a), None if b is None else np.array(b),
                             params)
    except MeasureError as exc:
        return [Reason(kind="no_match", subject="--points", message=(
            f"{exc}; give the points' right-image matches with --right-points"))], None
    if b is None:  # the matches found lie on the points' rows, at the found disparities
        found = rl - np.column_stack([got.disparities_px, np.zeros(len(a))])
        reasons = judge_geometry(_pixels(rl), _pixels(found), calib.rms_px)
    return reasons, None if reasons else got


def measure_points(calib: StereoCalibration, left: np.ndarray, right: np.ndarray,
                   pts_left: np.ndarray, pts_right: np.ndarray | None = None,
                   params: MeasureParams | None = None) -> PointDistance:
    """The 3-D distance between two points given in the raw left image, with its sd.

    Their right-image matches are given (raw right pixels) or found on the rectified pair
    by the same correlation as a detection's (a 25 x 25 patch around each point).
    """
    p = params or MeasureParams()
    a = np.asarray(pts_left, np.float64).reshape(-1, 2)
    if a.shape[0] != 2:
        raise MeasureError(f"points: expected two left-image points, got {a.shape[0]}")
    rig = calib.rig()
    rl = rectify_points(calib, a)
    if pts_right is not None:
        b = np.asarray(pts_right, np.float64).reshape(-1, 2)
        if b.shape[0] != 2:
            raise MeasureError(f"right points: expected two, got {b.shape[0]}")
        rr = rectify_points(calib, b, right=True)
        disp = [float(rl[i, 0] - rr[i, 0]) for i in range(2)]
        sds = [math.sqrt(2.0) * POINT_SD_PX] * 2  # both eyes' points are uncertain
    else:
        gl, gr = Rectifier(calib).apply(_grey(left), _grey(right))
        disp, sds = [], []
        for u, v in rl:
            x, y = int(round(u)), int(round(v))
            box = (x - MATCH_HALF_PX, y - MATCH_HALF_PX, x + MATCH_HALF_PX + 1,
                   y + MATCH_HALF_PX + 1)
            if box[0] < 0 or box[1] < 0 or box[2] > gl.shape[1] or box[3] > gl.shape[0]:
                raise MeasureError(f"point ({u:.1f}, {v:.1f}) (rectified): expected it at "
                                   f"least {MATCH_HALF_PX} px inside the image")
            got = match_ncc(gl, gr, box, rig, p)
            if isinstance(got, Unmeasured):
                raise MeasureError(f"point ({u:.1f}, {v:.1f}) (rectified): no right-image "
                                   f"match: {got.reason} ({got.detail})")
            # the patch's disparity belongs to its centre pixel (x, y); the point is at u
            disp.append(got.c)
            sds.append(math.sqrt(got.cov[0]))
    ends = [triangulate(rig, float(rl[i, 0]), float(rl[i, 1]), disp[i]) for i in range(2)]
    dist = float(np.linalg.norm(ends[0] - ends[1]))
    var = 0.0
    for i in range(2):
        for k, sd in ((0, POINT_SD_PX), (1, POINT_SD_PX), (2, sds[i])):
            q = [[float(rl[j, 0]), float(rl[j, 1]), disp[j]] for j in range(2)]
            q[i][k] += 0.01
            hi = float(np.linalg.norm(triangulate(rig, *q[0]) - triangulate(rig, *q[1])))
            q[i][k] -= 0.02
            lo = float(np.linalg.norm(triangulate(rig, *q[0]) - triangulate(rig, *q[1])))
            var += ((hi - lo) / 0.02 * sd) ** 2
    return PointDistance(a=_t(ends[0]), b=_t(ends[1]), distance_m=round(dist, 6),
                         distance_sd_m=round(math.sqrt(var), 6),
                         disparities_px=(round(disp[0], 3), round(disp[1], 3)))


def _t(p: np.ndarray) -> tuple[float, float, float]:
    return (round(float(p[0]), 6), round(float(p[1]), 6), round(float(p[2]), 6))


def _sizes(left: np.ndarray, right: np.ndarray) -> list[tuple[str, tuple[int, int]]]:
    return [("LEFT", (left.shape[1], left.shape[0])), ("RIGHT", (right.shape[1], right.shape[0]))]


def _pixels(pts: np.ndarray) -> list[tuple[float, float]]:
    return [(float(x), float(y)) for x, y in pts]


def _grey(img: np.ndarray) -> np.ndarray:
    return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
