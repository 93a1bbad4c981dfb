"""Hostile inputs to the real `trapflow measure` (a subprocess, as a person runs it): every
measurement that cannot be right is refused with its exit status and one line per reason
naming the point and the fix, and `--json` carries the verdict.

Regression: before the verdict, each of these printed a confident number with exit 0: a
match behind the rig ("z -1.26 m"), left and right points swapped ("2430.6 mm +- 15.0 mm"),
a match 200 px off its row, x = 5000 on a 640 px image, two identical points ("0.0 mm +-
0.0 mm"); and a board with LEFT and RIGHT swapped passed the field check.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable

import cv2
import numpy as np
import pytest

from tests.builders import rectified_calibration
from trapflow.calibration.camera import StereoRig
from trapflow.calibration.model import save_calibration
from trapflow.errors import EXIT_FAILURE, EXIT_OK, EXIT_USAGE
from trapflow.testing.checkerboard import render_pair

RIG = StereoRig.from_fov(640, 480, 70.0, 0.12)
PATTERN = (9, 6)
CLI_TIMEOUT_S = 60  # one measure is about 2 s; a hung one fails the test, not the suite


@pytest.fixture(scope="module")
def kit(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """calib.yaml, left.png, right.png (a flat board 0.6 m away), small.png (a quarter
    frame), and the board's two far corners in both images: l1 l2 r1 r2 as X,Y."""
    d = tmp_path_factory.mktemp("nonsense")
    left, right = render_pair(RIG, PATTERN, 0.03, np.array([0.1, -0.2, 0.05]),
                              np.array([-0.1, -0.07, 0.6]))
    for name, img in (("left.png", left), ("right.png", right), ("small.png", right[:240, :320])):
        cv2.imwrite(str(d / name), img)
    save_calibration(rectified_calibration(RIG), d / "calib.yaml")
    out = {name: str(d / name) for name in ("left.png", "right.png", "small.png", "calib.yaml")}
    for side, img in (("l", left), ("r", right)):
        ok, c = cv2.findChessboardCorners(img, PATTERN)
        assert ok
        for i, (x, y) in zip((1, 2), c.reshape(-1, 2)[[0, -1]], strict=True):
            out[f"{side}{i}"] = f"{x:.2f},{y:.2f}"
    return out


def measure(kit: dict[str, str], *args: str, left: str = "left.png",
            right: str = "right.png") -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "trapflow", "measure", "--calib", kit["calib.yaml"], kit[left],
         kit[right], *args], capture_output=True, text=True, timeout=CLI_TIMEOUT_S)


def shifted(point: str, dx: float = 0.0, dy: float = 0.0) -> str:
    x, y = (float(v) for v in point.split(","))
    return f"{x + dx:.2f},{y + dy:.2f}"


# Each case: the arguments (names from the kit fixture, built by a function of it), the
# images, the exit status, the (kind, subject) of every reason, and what its line must say.
Case = tuple[Callable[[dict[str, str]], list[str]], dict[str, str], int, list[tuple[str, str]],
             str]
CASES: dict[str, Case] = {
    # point 1's match 10 px right of it: a disparity of -10 px, behind the rig
    "negative disparity": (lambda k: ["--points", k["l1"], k["l2"], "--right-points",
                                      shifted(k["l1"], dx=10), k["r2"]],
                           {}, EXIT_FAILURE, [("behind", "point 1")],
                           "point 1: disparity -10.0 px after rectification puts it behind"),
    # point 2's match at the same pixel: zero disparity, at infinity
    "zero disparity": (lambda k: ["--points", k["l1"], k["l2"], "--right-points", k["r1"],
                                  k["l2"]],
                       {}, EXIT_FAILURE, [("behind", "point 2")], "puts it at infinity"),
    # the right image's points given as the left's and back
    "points swapped": (lambda k: ["--points", k["r1"], k["r2"], "--right-points", k["l1"],
                                  k["l2"]],
                       {}, EXIT_FAILURE, [("swapped", "points")], "look swapped: give the left"),
    # point 1's match 200 px below its row (rectified images: the same row)
    "off the epipolar row": (lambda k: ["--points", k["l1"], k["l2"], "--right-points",
                                        shifted(k["r1"], dy=200), k["r2"]],
                             {}, EXIT_FAILURE, [("off_row", "point 1")],
                             "point 1: its right match lies 200.0 px below its row"),
    # x = 5000 on a 640 px image: no match to find, nothing measured
    "point outside the image": (lambda k: ["--points", "5000,200", k["l2"]],
                                {}, EXIT_USAGE, [("outside_image", "--points")],
                                "Invalid value for --points: point 1 (5000, 200) lies outside "
                                "the 640x480 LEFT image: give a pixel of it"),
    "identical points": (lambda k: ["--points", k["l1"], k["l1"], "--right-points", k["r1"],
                                    k["r1"]],
                         {}, EXIT_USAGE, [("same_points", "--points")],
                         "give the two ends of the scale bar"),
    "image of another size": (lambda k: ["--points", k["l1"], k["l2"]],
                              {"right": "small.png"}, EXIT_USAGE, [("image_size", "RIGHT")],
                              "Invalid value for RIGHT: the image is 320x240, the "
                              "calibration 640x480"),
}


@pytest.mark.timeout(3 * CLI_TIMEOUT_S)
@pytest.mark.parametrize("case", list(CASES))
def test_nonsense_is_refused_with_its_reason(kit: dict[str, str], case: str) -> None:
    build, images, status, reasons, says = CASES[case]
    res = measure(kit, *build(kit), "--json", **images)
    assert res.returncode == status, (res.stdout, res.stderr)
    got = json.loads(res.stdout)
    assert got == {"verdict": got["verdict"]}  # no number where none can be right
    assert [(r["kind"], r["subject"]) for r in got["verdict"]] == reasons
    lines = res.stderr.splitlines()
    assert len(lines) == len(reasons), lines  # one line per reason, no traceback
    assert lines[0].startswith("trapflow: error: "), lines
    assert says in lines[0], lines


@pytest.mark.timeout(3 * CLI_TIMEOUT_S)
def test_a_board_with_left_and_right_swapped_fails(kit: dict[str, str]) -> None:
    """It passed: the corners' lengths are the same behind the rig as in front of it."""
    res = measure(kit, "--board", "9x6", "--square", "0.030", left="right.png",
                  right="left.png")
    assert res.returncode == EXIT_FAILURE, res.stdout
    assert res.stdout.splitlines()[-1].startswith("verdict: FAIL: corners at disparities -")
    assert "LEFT and RIGHT look swapped" in res.stdout
    got = json.loads(measure(kit, "--board", "9x6", "--square", "0.030", "--json",
                             left="right.png", right="left.png").stdout)
    assert [r["kind"] for r in got["verdict"]] == ["swapped"]
    assert got["disparities_px"][1] < 0


@pytest.mark.timeout(3 * CLI_TIMEOUT_S)
def test_without_json_a_refused_measurement_prints_no_number(kit: dict[str, str]) -> None:
    """The swapped points' "2430.6 mm +- 15.0 mm" is not printed at all."""
    res = measure(kit, "--points", kit["r1"], kit["r2"], "--right-points", kit["l1"],
                  kit["l2"])
    assert res.returncode == EXIT_FAILURE
    assert res.stdout == ""
    assert "swapped" in res.stderr


@pytest.mark.timeout(3 * CLI_TIMEOUT_S)
def test_a_sound_measurement_says_ok(kit: dict[str, str]) -> None:
    """The board's diagonal (283 mm) by its true corners: exit 0 and verdict "ok"."""
    res = measure(kit, "--points", kit["l1"], kit["l2"], "--right-points", kit["r1"],
                  kit["r2"], "--json")
    assert res.returncode == EXIT_OK, res.stderr
    got = json.loads(res.stdout)
    assert got["verdict"] == "ok"
    assert got["distance_m"] == pytest.approx(0.283, abs=0.003)
    assert res.stderr == ""

