"""`trapflow measure`: the field check of a calibration on one raw pair, a scale bar's two
points or a checkerboard's edges and diagonals (trapflow.measure.board does the measuring,
trapflow.measure.verdict says when a number cannot be right)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import click
import numpy as np

from trapflow.cli.sources import PatternType
from trapflow.errors import TrapflowError, unreachable
from trapflow.measure.verdict import Reason, exit_status

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
@click.option("--json", "as_json", is_flag=True,
              help="Print the measurement as JSON, with its verdict: \"ok\" or the reasons.")
@click.pass_context
def measure(ctx: click.Context, calib_path: str, left: np.ndarray, right: np.ndarray,
            points: tuple[tuple[float, float], ...] | None,
            right_points: tuple[tuple[float, float], ...] | None,
            pattern: tuple[int, int] | None, square: float | None, as_json: bool) -> None:
    """Check a calibration in the field: the 3-D distance between two points of the raw
    LEFT image (with its sd), or a checkerboard's error against its known squares and a
    verdict.

    \b
    Exit status 0: the measurement may be right.
    1: it cannot be right: a match behind the rig (the points or
       LEFT and RIGHT swapped) or off its row after rectification,
       or a board off its pass marks.
    2: nothing measured: an image of another size than the
       calibration, a point outside the image, two points in one,
       no match or no board found.
    Each reason is one line on stderr naming the point and the fix."""
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
    result: BoardCheck | PointDistance | None
    if pattern is not None:
        assert square is not None
        reasons, result = board.field_board(calib, left, right, pattern, square)
    else:
        assert points is not None
        reasons, result = board.field_points(
            calib, left, right, np.array(points),
            None if right_points is None else np.array(right_points))
    report(ctx, result, reasons, as_json)


def report(ctx: click.Context, result: BoardCheck | PointDistance | None,
           reasons: list[Reason], as_json: bool) -> None:
    """Print the measurement (text or JSON with its verdict) and, where it cannot be
    right, one line per reason on stderr; end with the verdict's exit status."""
    from trapflow.measure.board import PASS_TEXT, BoardCheck, PointDistance

    if as_json:
        click.echo(json_text(result, reasons))
    elif isinstance(result, BoardCheck):
        click.echo(board_text(result))
        click.echo(f"verdict: {'FAIL' if reasons else 'PASS'}: "
                   f"{'; '.join(r.message for r in reasons) or PASS_TEXT}")
    elif isinstance(result, PointDistance):
        click.echo(points_text(result))
    elif result is not None:
        unreachable(result)
    if not isinstance(result, BoardCheck):  # a board's failures are its verdict line
        for r in reasons:
            click.echo(f"trapflow: error: {ctx.command_path}: {reason_text(r)}", err=True)
    ctx.exit(exit_status(reasons))


def reason_text(r: Reason) -> str:
    """One line: an unusable input as click says it of an option, else the point first."""
    return f"Invalid value for {r.subject}: {r.message}" if r.usage else f"{r.subject}: {r.message}"


def json_text(result: BoardCheck | PointDistance | None, reasons: list[Reason]) -> str:
    """The measurement's fields (none where nothing could be measured) and `verdict`: "ok",
    or the reasons as {kind, subject, message}."""
    import msgspec

    out: dict[str, Any] = {} if result is None else msgspec.to_builtins(result)
    out["verdict"] = msgspec.to_builtins(reasons) if reasons else "ok"
    return msgspec.json.encode(out).decode()


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
