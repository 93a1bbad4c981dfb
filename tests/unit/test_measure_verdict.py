"""The field measurement's verdict, pure: inputs and rectified geometry in, reasons out.

Regression: `trapflow measure --points` printed confident nonsense with exit 0 for a match
behind the rig, left and right points swapped, a match 200 px off its row, a point outside
the image and two identical points; `--board` passed LEFT and RIGHT swapped. Each row says
which reason (kind, subject) the verdict must give, in order; [] is "ok".
"""

from __future__ import annotations

import math

import pytest

from trapflow.errors import EXIT_FAILURE, EXIT_OK, EXIT_USAGE
from trapflow.measure.board import BoardCheck, board_reasons
from trapflow.measure.verdict import (
    ROW_FLOOR_PX,
    Reason,
    exit_status,
    judge_geometry,
    judge_inputs,
    row_tolerance_px,
)

SIZE = (640, 480)
SIZES = [("LEFT", SIZE), ("RIGHT", SIZE)]
A, B = (300.0, 200.0), (400.0, 210.0)


def kinds(reasons: list[Reason]) -> list[tuple[str, str]]:
    return [(r.kind, r.subject) for r in reasons]


@pytest.mark.parametrize(("images", "left", "right", "expected"), [
    (SIZES, [A, B], [A, B], []),  # two distinct points inside both images
    (SIZES, [A, B], None, []),  # right points to be found by correlation: only the left's
    ([("LEFT", (320, 240)), ("RIGHT", SIZE)], [A, B], None,
     [("image_size", "LEFT")]),  # a reduced frame
    ([("LEFT", (640, 360)), ("RIGHT", (1280, 720))], [A, B], None,
     [("image_size", "LEFT"), ("image_size", "RIGHT")]),  # each image said
    (SIZES, [(5000.0, 200.0), B], None, [("outside_image", "--points")]),  # x = 5000 of 640
    (SIZES, [A, B], [A, (400.0, -3.0)], [("outside_image", "--right-points")]),  # above
    (SIZES, [(-0.5, 0.0), (639.5, 479.5)], None, []),  # the pixel area's very edges
    (SIZES, [(-0.6, 0.0), (639.6, 479.5)], None,
     [("outside_image", "--points"), ("outside_image", "--points")]),  # just past them
    (SIZES, [(math.nan, 200.0), B], None, [("outside_image", "--points")]),  # nan is no pixel
    (SIZES, [A, (math.inf, 1.0)], None, [("outside_image", "--points")]),  # nor is inf
    (SIZES, [A, A], [B, B], [("same_points", "--points")]),  # identical: "0.0 mm +- 0.0 mm"
    (SIZES, [A, (300.6, 200.6)], None, [("same_points", "--points")]),  # 0.85 px: unresolved
    (SIZES, [A, (301.0, 200.0)], None, []),  # 1 px apart: two points
])
def test_inputs(images: list[tuple[str, tuple[int, int]]], left: list[tuple[float, float]],
                right: list[tuple[float, float]] | None,
                expected: list[tuple[str, str]]) -> None:
    got = judge_inputs(SIZE, images, left, right)
    assert kinds(got) == expected
    assert all(r.usage for r in got)  # nothing here was measured: usage errors, exit 2


@pytest.mark.parametrize(("left", "right", "rms", "expected"), [
    ([A, B], [(250.0, 200.0), (350.0, 210.0)], 0.2, []),  # 50 px in front, on their rows
    ([A, B], [(310.0, 200.0), (350.0, 210.0)], 0.2, [("behind", "point 1")]),  # -10 px
    ([A, B], [(250.0, 200.0), (400.0, 210.0)], 0.2, [("behind", "point 2")]),  # 0: infinity
    ([A, B], [(350.0, 200.0), (450.0, 210.0)], 0.2, [("swapped", "points")]),  # both < 0:
    # one reason for the pair, not one a point
    ([A, B], [(250.0, 200.0), (350.0, 410.0)], 0.2, [("off_row", "point 2")]),  # 200 px off
    ([A, B], [(350.0, 400.0), (450.0, 210.0)], 0.2,
     [("swapped", "points"), ("off_row", "point 1")]),  # both said
    ([A, B], [(250.0, 202.0), (350.0, 208.0)], None, []),  # 2 px: within 2.1 (points only)
    ([A, B], [(250.0, 202.5), (350.0, 210.0)], None, [("off_row", "point 1")]),  # 2.5 > 2.1
    ([A, B], [(250.0, 202.5), (350.0, 210.0)], 0.6, []),  # a 0.6 px calibration: 2.8 px
    ([A, B], [(250.0, 204.0), (350.0, 210.0)], 0.6, [("off_row", "point 1")]),  # 4 > 2.8
])
def test_geometry(left: list[tuple[float, float]], right: list[tuple[float, float]],
                  rms: float | None, expected: list[tuple[str, str]]) -> None:
    got = judge_geometry(left, right, rms)
    assert kinds(got) == expected
    assert not any(r.usage for r in got)  # measurable, but cannot be right: exit 1


@pytest.mark.parametrize(("rms", "expected"), [
    (None, 3 * math.sqrt(0.5)),  # the two points' own 0.5 px, 3 sd: 2.12 px
    (0.0, 3 * math.sqrt(0.5)),
    (0.205, 3 * math.hypot(math.sqrt(0.5), 0.205)),  # the kit's OpenCV set: 2.21 px
    (0.605, 3 * math.hypot(math.sqrt(0.5), 0.605)),  # the kit's rational reference: 2.79
    (2.0, 3 * math.hypot(math.sqrt(0.5), 2.0)),  # a poor calibration widens it: 6.36
])
def test_row_tolerance_grows_with_the_calibration_error(rms: float | None,
                                                        expected: float) -> None:
    assert row_tolerance_px(rms) == pytest.approx(expected)
    assert row_tolerance_px(rms) >= ROW_FLOOR_PX


def test_every_message_is_one_line_with_a_fix() -> None:
    reasons = (judge_inputs(SIZE, [("LEFT", (1, 1))], [(5000.0, 0.0), (5000.0, 0.0)], None)
               + judge_geometry([A, B], [(350.0, 400.0), (250.0, 210.0)], 0.3))
    assert len(reasons) == 6
    for r in reasons:
        assert "\n" not in r.message
        assert "give" in r.message or "check" in r.message, r.message


@pytest.mark.parametrize(("reasons", "expected"), [
    ([], EXIT_OK),
    ([Reason(kind="behind", subject="point 1", message="m")], EXIT_FAILURE),
    ([Reason(kind="diagonal", subject="board", message="m")], EXIT_FAILURE),
    ([Reason(kind="behind", subject="point 1", message="m"),
      Reason(kind="outside_image", subject="--points", message="m")], EXIT_USAGE),
])
def test_exit_status(reasons: list[Reason], expected: int) -> None:
    assert exit_status(reasons) == expected


def board(**change: object) -> BoardCheck:
    """A board check that passes every mark, with the fields named changed."""
    fields: dict[str, object] = dict(
        pattern=(9, 6), square_m=0.03, edges_m=[0.03] * 93, edge_rms_mm=0.2, edge_max_mm=0.5,
        diagonals_m=(0.283, 0.283), diagonal_m=0.283, diagonal_err_pct=(0.1, -0.2),
        rectified_dy_px=0.2, disparities_px=(80.0, 95.0))
    fields.update(change)
    return BoardCheck(**fields)  # type: ignore[arg-type]


@pytest.mark.parametrize(("check", "expected"), [
    (board(), []),
    (board(edge_rms_mm=6.0), ["edges"]),  # 20 %: the wrong --square
    (board(diagonal_err_pct=(0.1, -2.5)), ["diagonal"]),  # pair 01's with a 23 px window
    (board(rectified_dy_px=1.5), ["rows"]),  # a camera moved in its housing
    (board(disparities_px=(-91.7, -82.9)), ["swapped"]),  # LEFT and RIGHT swapped: it passed
    (board(disparities_px=(-5.0, 3.0), edge_rms_mm=6.0, diagonal_err_pct=(3.0, 0.0)),
     ["swapped", "edges", "diagonal"]),  # every mark missed is said
])
def test_board_reasons(check: BoardCheck, expected: list[str]) -> None:
    assert [r.kind for r in board_reasons(check)] == expected
