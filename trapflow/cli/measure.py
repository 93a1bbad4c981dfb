"""`trapflow measure`: the field check of a calibration on one raw pair, a scale bar's two
points or a checkerboard's edges and diagonals (trapflow.measure.board does the measuring)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import click
import numpy as np

from trapflow.cli.sources import PatternType
from trapflow.errors import TrapflowError

if TYPE_CHECKING:  # the measuring code (OpenCV) loads when the command runs
    from trapflow.measure.board import BoardCheck, PointDistance


class PointType(click.ParamType[tuple[float, float]]):
    """`X,Y`: a pixel of the raw image (OpenCV's convention, a pixel's centre at integers)."""

    name = "X,Y"

    def convert(self, value: Any, param: click.Parameter | None,
                ctx: click.Context | None) -> tuple[float, float]:
        if isinstance(value, tuple):
            return value
        x, sep, y = str(value).partition(",")
        try:
            if not sep:
                raise ValueError
            return float(x), float(y)
        except ValueError:
            self.fail(f"expected a pixel X,Y such as 412.5,230, got {value!r}", param, ctx)


class ImageType(click.ParamType[np.ndarray]):
    """An image file OpenCV reads, loaded grey."""

    name = "IMAGE"

    def convert(self, value: Any, param: click.Parameter | None,
                ctx: click.Context | None) -> np.ndarray:
        if isinstance(value, np.ndarray):
            return value
        import cv2

        img = cv2.imread(str(value), cv2.IMREAD_GRAYSCALE) if Path(value).is_file() else None
        if img is None:
            self.fail(f"cannot read {str(value)!r} as an image: expected a PNG, JPEG or "
                      "other file OpenCV reads (the raw, unrectified frame)", param, ctx)
        return np.asarray(img)


@click.command("measure")
@click.option("--calib", "calib_path", required=True,
              help="The rig's stereo calibration (trapflow calibrate's YAML, a camera_info "
                   "pair LEFT,RIGHT, or a folder; see docs/calibration.md).")
@click.argument("left", type=ImageType())
@click.argument("right", type=ImageType())
@click.option("--points", type=PointType(), nargs=2, default=None, metavar="X1,Y1 X2,Y2",
              help="Two points of the left image (a scale bar's ends): their 3-D distance.")
@click.option("--right-points", type=PointType(), nargs=2, default=None,
              metavar="X1,Y1 X2,Y2",
              help="The same two points in the right image (default: found by correlation).")
@click.option("--board", "pattern", type=PatternType(), default=None,
              help="A checkerboard's inner corners per row x per column, e.g. 9x6: every "
                   "edge and diagonal against --square.")
@click.option("--square", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Side of one square of the --board in metres, e.g. 0.030.")
@click.option("--json", "as_json", is_flag=True, help="Print the measurement as JSON.")
@click.pass_context
def measure(ctx: click.Context, calib_path: str, left: np.ndarray, right: np.ndarray,
            points: tuple[tuple[float, float], ...] | None,
            right_points: tuple[tuple[float, float], ...] | None,
            pattern: tuple[int, int] | None, square: float | None, as_json: bool) -> None:
    """Check a calibration in the field: the 3-D distance between two points of the raw
    LEFT image (with its sd), or a checkerboard's error against its known squares and a
    verdict (exit status 1 when the rig no longer measures right)."""
    import msgspec

    from trapflow.calibration.formats import load_calibration
    from trapflow.measure import board

    if (points is None) == (pattern is None):
        raise click.UsageError("expected one of --points X1,Y1 X2,Y2 (a scale bar) or "
                               "--board WxH --square S (a checkerboard)")
    if pattern is not None and (square is None or right_points is not None):
        raise click.UsageError("--board measures against --square S (metres), and finds "
                               "the corners itself: give --square, not --right-points")
    if points is not None and square is not None:
        raise click.UsageError("--square goes with --board; --points measures any distance")
    try:
        calib = load_calibration(calib_path)
    except TrapflowError as exc:
        raise click.BadParameter(str(exc), param_hint="--calib") from None
    for name, img in (("LEFT", left), ("RIGHT", right)):
        size = (img.shape[1], img.shape[0])
        if size != calib.size:
            raise click.BadParameter(
                f"the image is {size[0]}x{size[1]}, the calibration {calib.size[0]}x"
                f"{calib.size[1]}: give the raw frames of the calibrated cameras, or "
                "calibrate at this size (trapflow calibrate)", param_hint=name)
    result: BoardCheck | PointDistance
    try:
        if pattern is not None:
            assert square is not None
            result = board.check_board(calib, left, right, pattern, square)
        else:
            assert points is not None
            result = board.measure_points(
                calib, left, right, np.array(points),
                None if right_points is None else np.array(right_points))
    except board.MeasureError as exc:
        fix = ("; give the board's inner corners (--board 9x6 for 10 x 7 squares) with the "
               "whole board in both images" if pattern is not None else
               "; give the points' right-image matches with --right-points")
        raise click.UsageError(f"{exc}{fix}") from None
    if as_json:
        click.echo(msgspec.json.encode(result).decode())
    if isinstance(result, board.PointDistance):
        if not as_json:
            click.echo(points_text(result))
        return
    ok, why = board.verdict(result)
    if not as_json:
        click.echo(board_text(result))
        click.echo(f"verdict: {'PASS' if ok else 'FAIL'}: {why}")
    if not ok:
        ctx.exit(1)


def points_text(d: PointDistance) -> str:
    """The distance, its sd and both 3-D points (rectified left camera frame)."""
    lines = [f"distance: {1000 * d.distance_m:.1f} mm +- {1000 * d.distance_sd_m:.1f} mm (1 sd)"]
    for name, p, disp in (("point 1", d.a, d.disparities_px[0]),
                          ("point 2", d.b, d.disparities_px[1])):
        lines.append(f"{name}: x {p[0]:+.4f} y {p[1]:+.4f} z {p[2]:.4f} m "
                     f"(disparity {disp:.2f} px)")
    return "\n".join(lines)


def board_text(c: BoardCheck) -> str:
    """Edges (RMS and largest error in mm), both diagonals (in %), rows after rectification."""
    cols, rows = c.pattern
    d1, d2 = c.diagonals_m
    e1, e2 = c.diagonal_err_pct
    return "\n".join([
        f"board {cols}x{rows}, squares {1000 * c.square_m:.1f} mm",
        f"edges: {len(c.edges_m)}, RMS error {c.edge_rms_mm:.2f} mm, largest "
        f"{c.edge_max_mm:.2f} mm",
        f"diagonals: {1000 * d1:.1f} mm ({e1:+.2f} %), {1000 * d2:.1f} mm ({e2:+.2f} %) "
        f"of {1000 * c.diagonal_m:.1f} mm",
        f"rows after rectification: {c.rectified_dy_px:.2f} px RMS apart",
    ])


COMMANDS = (measure,)
