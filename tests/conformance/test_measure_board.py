"""The board check on OpenCV's own stereo sample set, against an independent triangulation.

The set (01_stereo_checkerboard_opencv): 13 real 640x480 pairs of a 9x6 board whose squares
are 30 mm. trapflow calibrates on 9 of them with square 0.030 and measures the 4 held out;
the reference triangulates the same corners with OpenCV's undistortPoints and
triangulatePoints from the same calibration, written here without trapflow's code.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from trapflow.calibration.calibrate import calibrate_stereo
from trapflow.calibration.model import StereoCalibration, save_calibration
from trapflow.cli.main import main
from trapflow.measure.board import (
    MeasureError,
    board_edges,
    board_reasons,
    check_board,
    measure_points,
)
from trapflow.measure.stereo import MeasureParams

from .conftest import kit_path

SET = "01_stereo_checkerboard_opencv"
PATTERN = (9, 6)
SQUARE = 0.030
HELD_OUT = ("03", "08", "12", "14")
log = logging.getLogger(__name__)


def pairs(root: Path) -> tuple[list[tuple[Path, Path]], list[tuple[Path, Path]]]:
    """(calibration pairs, held-out pairs) of the kit's set."""
    images = kit_path(root, SET, "images")
    all_ = [(p, images / p.name.replace("left", "right"))
            for p in sorted(images.glob("left*.jpg"))]
    held = [(a, b) for a, b in all_ if a.stem[-2:] in HELD_OUT]
    return [pr for pr in all_ if pr not in held], held


@pytest.fixture(scope="module")
def calibrated() -> tuple[StereoCalibration, list[tuple[Path, Path]]]:
    from .conftest import realdata_root

    root = realdata_root()
    if not (root / "MANIFEST.md").is_file():
        pytest.skip(f"real-data kit not found at {root} (set TRAPFLOW_REALDATA to its folder)")
    train, held = pairs(root)
    report = calibrate_stereo([a for a, _ in train], [b for _, b in train], PATTERN, SQUARE)
    assert report.rejected == []
    return report.calibration, held


def reference_points(calib: StereoCalibration, left: np.ndarray, right: np.ndarray
                     ) -> np.ndarray:
    """OpenCV alone: corners (refined in trapflow calibrate's 11 x 11 window), undistortPoints
    with R1/P1 and R2/P2, triangulatePoints."""
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    corners = []
    for img in (left, right):
        ok, c = cv2.findChessboardCorners(img, PATTERN, flags=flags)
        assert ok
        corners.append(cv2.cornerSubPix(img, c, (5, 5), (-1, -1), crit).reshape(-1, 2))
    cl, cr = corners
    if float(np.dot(cl[-1] - cl[0], cr[-1] - cr[0])) < 0:  # the board's other corner order
        cr = cr[::-1]
    a = calib.arr
    ul = cv2.undistortPoints(cl.reshape(-1, 1, 2), a("K1"), a("D1"), R=a("R1"), P=a("P1"))
    ur = cv2.undistortPoints(cr.reshape(-1, 1, 2), a("K2"), a("D2"), R=a("R2"), P=a("P2"))
    h = cv2.triangulatePoints(a("P1"), a("P2"), ul.reshape(-1, 2).T, ur.reshape(-1, 2).T)
    out: np.ndarray = (h[:3] / h[3]).T
    return out


@pytest.mark.timeout(120)
def test_held_out_boards_measure_within_targets_and_agree_with_opencv(
        calibrated: tuple[StereoCalibration, list[tuple[Path, Path]]]) -> None:
    """RMS edge error <= 1.5 mm on 30 mm squares, diagonals (283 mm) within 1 %, and every
    edge within 0.1 mm of OpenCV's own triangulation of the same corners."""
    calib, held = calibrated
    assert calib.baseline_m == pytest.approx(0.0998, abs=0.002)  # the author's 99.8 mm
    for lp, rp in held:
        left = cv2.imread(str(lp), cv2.IMREAD_GRAYSCALE)
        right = cv2.imread(str(rp), cv2.IMREAD_GRAYSCALE)
        check = check_board(calib, left, right, PATTERN, SQUARE)
        ref = board_edges(reference_points(calib, left, right), PATTERN)
        diff_mm = 1000 * np.abs(np.array(check.edges_m) - ref)
        log.info("%s: edge rms %.3f mm (max %.3f), diagonals %+.3f %% %+.3f %%, rectified dy "
                 "%.3f px, trapflow - OpenCV max %.4f mm", lp.name, check.edge_rms_mm,
                 check.edge_max_mm, *check.diagonal_err_pct, check.rectified_dy_px,
                 diff_mm.max())
        assert check.edge_rms_mm <= 1.5, lp.name
        assert max(abs(e) for e in check.diagonal_err_pct) <= 1.0, lp.name
        assert diff_mm.max() <= 0.1, lp.name


@pytest.mark.timeout(120)
def test_every_pair_of_the_set_passes_the_field_check(
        calibrated: tuple[StereoCalibration, list[tuple[Path, Path]]]) -> None:
    """Pairs 01 and 02, views the rig was calibrated on, failed the check (diagonals -2.5 %
    and +1.9 %, limit 1 %): the check refined corners in a 23 x 23 px window, which reached
    past the set's smallest squares (22 px) and moved end corners of a row by 2.5-6.4 px off
    the points the calibration was fitted to. With the calibration's own 11 x 11 window every
    pair of the 13, the 9 calibrated on and the 4 held out, passes."""
    from .conftest import realdata_root

    calib, _ = calibrated
    train, held = pairs(realdata_root())
    for lp, rp in train + held:
        left = cv2.imread(str(lp), cv2.IMREAD_GRAYSCALE)
        right = cv2.imread(str(rp), cv2.IMREAD_GRAYSCALE)
        assert left is not None and right is not None
        check = check_board(calib, left, right, PATTERN, SQUARE)
        assert board_reasons(check) == [], (lp.name, check.diagonal_err_pct)
        assert max(abs(e) for e in check.diagonal_err_pct) <= 0.8, lp.name  # measured 0.70


@pytest.mark.timeout(120)
def test_two_points_matched_by_correlation_measure_the_board_diagonal(
        calibrated: tuple[StereoCalibration, list[tuple[Path, Path]]]) -> None:
    """measure_points with no right points: the two far corners of held-out board 14, their
    right matches found by correlation, give the 283 mm diagonal within 1 % and 2 sd; on
    board 12 a corner's patch repeats along its row (the squares) and is refused as
    ambiguous rather than measured."""
    calib, held = calibrated
    params = MeasureParams(min_range_m=0.15)  # the boards are held 0.3 to 0.6 m away
    found = dict((lp.stem[-2:], (lp, rp)) for lp, rp in held)
    want = SQUARE * float(np.hypot(PATTERN[0] - 1, PATTERN[1] - 1))
    for name in ("14", "12"):
        lp, rp = found[name]
        left = cv2.imread(str(lp), cv2.IMREAD_GRAYSCALE)
        right = cv2.imread(str(rp), cv2.IMREAD_GRAYSCALE)
        ok, c = cv2.findChessboardCorners(left, PATTERN)
        assert ok
        pts = c.reshape(-1, 2)[[0, -1]]
        if name == "12":
            with pytest.raises(MeasureError, match="ambiguous"):
                measure_points(calib, left, right, pts, params=params)
            continue
        got = measure_points(calib, left, right, pts, params=params)
        log.info("diagonal by correlation: %.4f m +- %.4f (want %.4f)", got.distance_m,
                 got.distance_sd_m, want)
        assert got.distance_m == pytest.approx(want, rel=0.01)
        assert abs(got.distance_m - want) <= 2 * got.distance_sd_m


@pytest.mark.timeout(120)
def test_measure_command_on_held_out_boards(
        calibrated: tuple[StereoCalibration, list[tuple[Path, Path]]], tmp_path: Path) -> None:
    """`trapflow measure --board 9x6 --square 0.030` on the held-out pairs, with the
    calibration written as `trapflow calibrate --square 0.030` writes it: RMS <= 1.5 mm on
    the 30 mm edges, diagonals within 1 %, a PASS verdict, and the library's own numbers."""
    calib, held = calibrated
    path = tmp_path / "calib.yaml"
    save_calibration(calib, path)
    for lp, rp in held:
        args = ["measure", "--calib", str(path), str(lp), str(rp), "--board", "9x6",
                "--square", "0.030"]
        res = CliRunner().invoke(main, args)
        assert res.exit_code == 0, res.output
        log.info("%s: %s", lp.name, res.output.strip().replace("\n", " | "))
        assert res.output.splitlines()[-1].startswith("verdict: PASS")
        got = json.loads(CliRunner().invoke(main, [*args, "--json"]).output)
        assert got["edge_rms_mm"] <= 1.5, lp.name
        assert max(abs(e) for e in got["diagonal_err_pct"]) <= 1.0, lp.name
        left = cv2.imread(str(lp), cv2.IMREAD_GRAYSCALE)
        right = cv2.imread(str(rp), cv2.IMREAD_GRAYSCALE)
        assert got["edges_m"] == check_board(calib, left, right, PATTERN, SQUARE).edges_m
