"""The verdict on a field measurement: whether `trapflow measure` may give a number, or the
reasons it cannot (each one line naming the point, what is wrong and the fix).

Pure: image sizes, the points as given, the points rectified and the calibration's own error
in, a list of Reason out (empty: the measurement may be right). board.py rectifies, measures
and calls these; the command prints the reasons and exits with exit_status().
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

import msgspec

from trapflow.errors import EXIT_FAILURE, EXIT_OK, EXIT_USAGE

Pixel = tuple[float, float]
Size = tuple[int, int]
Kind = Literal["image_size", "outside_image", "same_points", "no_match", "no_board",
               "behind", "swapped", "off_row", "edges", "diagonal", "rows"]
# The inputs cannot be measured as given (exit 2): nothing was measured. Every other kind
# is a measurement that cannot be right (exit 1).
USAGE_KINDS: frozenset[Kind] = frozenset(
    {"image_size", "outside_image", "same_points", "no_match", "no_board"})

POINT_SD_PX = 0.5  # a point a person gives: half a pixel each way
# Two left points closer than their own uncertainty (2 x 0.5 px) name no distance.
SAME_POINT_PX = 2 * POINT_SD_PX
# A rectified pair puts a point and its match on one row, up to the points' own error
# (sqrt(2) x 0.5 px on a difference of two) and the calibration's (its reprojection RMS is
# per 2-D point, rms/sqrt(2) per coordinate, so rms on the difference of the two eyes'
# rows). A match further than ROW_SDS of that off its row is another point; a true match is
# refused about 3 times in 1000.
ROW_SDS = 3.0
# The floor: twice the board check's 1 px RMS limit on rows (a calibration that passes it
# may leave a single point's row that far off), and a click a pixel or two off.
ROW_FLOOR_PX = 2.0


class Reason(msgspec.Struct, frozen=True, kw_only=True):
    """Why a measurement cannot be made, or cannot be right."""

    kind: Kind
    subject: str  # an input (LEFT, RIGHT, --points, --right-points, --board) or a point
    message: str  # what is wrong, with its numbers, and the fix

    @property
    def usage(self) -> bool:
        """Whether the inputs were unusable (exit 2) rather than the result impossible (1)."""
        return self.kind in USAGE_KINDS


def exit_status(reasons: Sequence[Reason]) -> int:
    """0 with no reason, 2 when an input cannot be used, else 1."""
    if not reasons:
        return EXIT_OK
    return EXIT_USAGE if any(r.usage for r in reasons) else EXIT_FAILURE


def row_tolerance_px(rms_px: float | None) -> float:
    """How far (px) a point's rectified match may lie off its row, from the calibration's
    reprojection RMS (None where the calibration carries none: the points' error alone)."""
    sd = math.hypot(math.sqrt(2.0) * POINT_SD_PX, rms_px or 0.0)
    return max(ROW_FLOOR_PX, ROW_SDS * sd)


def judge_sizes(calib_size: Size, images: Sequence[tuple[str, Size]]) -> list[Reason]:
    """Each image (name, (w, h)) against the calibration's size."""
    cw, ch = calib_size
    return [Reason(kind="image_size", subject=name,
                   message=f"the image is {w}x{h}, the calibration {cw}x{ch}: give the raw "
                           "frames of the calibrated cameras, or calibrate at this size "
                           "(trapflow calibrate)")
            for name, (w, h) in images if (w, h) != calib_size]


def judge_inputs(calib_size: Size, images: Sequence[tuple[str, Size]], left: Sequence[Pixel],
                 right: Sequence[Pixel] | None) -> list[Reason]:
    """What can be told before measuring: the images' sizes, every point inside its raw
    image, and two left points that are two points."""
    out = judge_sizes(calib_size, images)
    sides = [("--points", "LEFT", left)] + ([] if right is None else
                                            [("--right-points", "RIGHT", right)])
    w, h = calib_size
    for option, image, pts in sides:
        for i, (x, y) in enumerate(pts, 1):
            # A pixel's centre sits at integer coordinates: its area reaches half a pixel out.
            if not (-0.5 <= x <= w - 0.5 and -0.5 <= y <= h - 0.5):
                out.append(Reason(kind="outside_image", subject=option, message=(
                    f"point {i} ({x:g}, {y:g}) lies outside the {w}x{h} {image} image: give "
                    f"a pixel of it, x from 0 to {w - 1} and y from 0 to {h - 1}")))
    if len(left) == 2 and math.dist(left[0], left[1]) < SAME_POINT_PX:
        out.append(Reason(kind="same_points", subject="--points", message=(
            f"points 1 and 2 ({left[0][0]:g}, {left[0][1]:g}) and ({left[1][0]:g}, "
            f"{left[1][1]:g}) are {math.dist(left[0], left[1]):.2f} px apart, within their "
            f"own error ({SAME_POINT_PX:g} px): give the two ends of the scale bar")))
    return out


def judge_geometry(left: Sequence[Pixel], right: Sequence[Pixel],
                   rms_px: float | None) -> list[Reason]:
    """Rectified points and their right-image matches: every match left of its point (a
    positive disparity: in front of the rig) and on its row (within row_tolerance_px)."""
    out: list[Reason] = []
    disp = [a[0] - b[0] for a, b in zip(left, right, strict=True)]
    if len(disp) > 1 and all(d < 0 for d in disp):
        shown = ", ".join(f"{d:.1f}" for d in disp)
        out.append(Reason(kind="swapped", subject="points", message=(
            f"every point has a negative disparity ({shown} px: each match lies right of its "
            "point after rectification, so behind the rig): the left and right points, or "
            "the LEFT and RIGHT images, look swapped: give the left camera's frame and its "
            "points first (LEFT, --points), the right camera's second (RIGHT, --right-points)")))
    else:
        for i, d in enumerate(disp, 1):
            if d <= 0:
                where = "at infinity" if d == 0 else "behind the rig"
                out.append(Reason(kind="behind", subject=f"point {i}", message=(
                    f"disparity {d:.1f} px after rectification puts it {where} (a point in "
                    "front of the rig lies further left in the right image): its right "
                    f"match is another point; give the right image's match of point {i} "
                    "(--right-points)")))
    tol = row_tolerance_px(rms_px)
    source = "the points' own error" if rms_px is None else (
        f"the calibration's {rms_px:.2f} px RMS and the points' own error")
    for i, (a, b) in enumerate(zip(left, right, strict=True), 1):
        dy = b[1] - a[1]
        if abs(dy) > tol:
            out.append(Reason(kind="off_row", subject=f"point {i}", message=(
                f"its right match lies {abs(dy):.1f} px {'below' if dy > 0 else 'above'} its "
                f"row after rectification (tolerance {tol:.1f} px, from {source}): a point "
                "and its match share a row; give the right image's match of point "
                f"{i} (--right-points), or, if every point is off, check the calibration "
                "(--board)")))
    return out
