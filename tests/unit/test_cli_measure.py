"""`trapflow measure` through click: a board rendered through a known rig, its calibration
exact, measured as a scale bar and as a board; every bad input a usage error (exit 2)."""

from __future__ import annotations

import json
import re

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from tests.builders import rectified_calibration
from trapflow.calibration.camera import StereoRig
from trapflow.calibration.model import save_calibration
from trapflow.cli.main import main
from trapflow.testing.checkerboard import render_pair

RIG = StereoRig.from_fov(640, 480, 70.0, 0.12)
PATTERN = (9, 6)
SQUARE = 0.03
DIAGONAL = SQUARE * float(np.hypot(8, 5))  # 283.0 mm


@pytest.fixture(scope="module")
def kit(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """calib.yaml, left.png, right.png (a board 0.6 m away, tilted), a blank and a text file,
    and the board's two far corners in both images."""
    d = tmp_path_factory.mktemp("measure")
    left, right = render_pair(RIG, PATTERN, SQUARE, np.array([0.1, -0.2, 0.05]),
                              np.array([-0.1, -0.07, 0.6]))
    cv2.imwrite(str(d / "left.png"), left)
    cv2.imwrite(str(d / "right.png"), right)
    cv2.imwrite(str(d / "blank.png"), np.full((480, 640), 120, np.uint8))
    cv2.imwrite(str(d / "small.png"), left[:240, :320])
    (d / "notes.txt").write_text("not an image\n")
    save_calibration(rectified_calibration(RIG), d / "calib.yaml")
    out = {name: str(d / name) for name in ("left.png", "right.png", "blank.png", "small.png",
                                             "notes.txt", "calib.yaml")}
    for side, img in (("l", left), ("r", right)):
        ok, c = cv2.findChessboardCorners(img, PATTERN)
        assert ok
        a, b = c.reshape(-1, 2)[[0, -1]]
        out[f"{side}1"], out[f"{side}2"] = f"{a[0]:.2f},{a[1]:.2f}", f"{b[0]:.2f},{b[1]:.2f}"
    return out


def run(kit: dict[str, str], *args: str, left: str = "left.png", right: str = "right.png",
        calib: str = "calib.yaml") -> tuple[int, str]:
    res = CliRunner().invoke(main, ["measure", "--calib", kit.get(calib, calib),
                                    kit.get(left, left), kit.get(right, right), *args])
    return res.exit_code, res.output


def test_board_prints_its_errors_and_passes(kit: dict[str, str]) -> None:
    code, out = run(kit, "--board", "9x6", "--square", "0.030")
    assert code == 0, out
    lines = out.splitlines()
    assert lines[0] == "board 9x6, squares 30.0 mm"
    assert lines[1].startswith("edges: 93, RMS error ")
    assert float(lines[1].split("RMS error ")[1].split()[0]) <= 1.0  # measured 0.40 mm
    assert lines[-1].startswith("verdict: PASS: ")


def test_board_json_has_the_numbers(kit: dict[str, str]) -> None:
    code, out = run(kit, "--board", "9x6", "--square", "0.030", "--json")
    assert code == 0, out
    got = json.loads(out)
    assert len(got["edges_m"]) == 93 and got["diagonal_m"] == pytest.approx(DIAGONAL, abs=1e-6)
    assert max(abs(e) for e in got["diagonal_err_pct"]) < 1.0


def test_a_wrong_square_fails_the_verdict(kit: dict[str, str]) -> None:
    """30 mm squares said to be 25 mm: every edge 20 % long, exit status 1."""
    code, out = run(kit, "--board", "9x6", "--square", "0.025")
    assert code == 1
    assert out.splitlines()[-1].startswith("verdict: FAIL: edges off by ")


@pytest.mark.parametrize("given", ["right", "matched"])
def test_two_points_measure_the_board_diagonal(kit: dict[str, str], given: str) -> None:
    extra = ["--right-points", kit["r1"], kit["r2"]] if given == "right" else []
    code, out = run(kit, "--points", kit["l1"], kit["l2"], *extra)
    assert code == 0, out
    first = out.splitlines()[0]  # distance: 283.3 mm +- 1.0 mm (1 sd)
    mm, sd = float(first.split()[1]), float(first.split()[4])
    assert abs(mm - 1000 * DIAGONAL) <= max(2 * sd, 1.5)
    assert 0 < sd < 5
    assert out.count("disparity") == 2


@pytest.mark.parametrize(
    ("args", "files", "error"),
    [
        # what was wrong, and the fix, on click's usage error
        ([], {}, "expected one of --points X1,Y1 X2,Y2 .* or --board WxH --square S"),
        (["--board", "9x6"], {}, "give --square"),
        (["--board", "9x6", "--square", "0.03", "--points", "1,1", "2,2"], {},
         "expected one of"),
        (["--points", "1,1", "2,2", "--square", "0.03"], {}, "--square goes with --board"),
        (["--points", "10;20", "30,40"], {}, r"expected a pixel X,Y such as 412.5,230, got "
         r"'10;20'"),
        (["--points", "a,b", "30,40"], {}, "expected a pixel X,Y"),
        (["--board", "nine", "--square", "0.03"], {}, "Invalid value for '--board'"),
        (["--board", "9x6", "--square", "0.03"], {"left": "notes.txt"},
         r"cannot read '.*notes.txt' as an image: expected a PNG, JPEG"),
        (["--board", "9x6", "--square", "0.03"], {"right": "missing.png"},
         "cannot read 'missing.png' as an image"),
        (["--board", "9x6", "--square", "0.03"], {"left": "blank.png"},
         "expected it in the left image, found none; give the board's inner corners"),
        (["--board", "7x5", "--square", "0.03"], {}, "board 7x5 .*found none"),
        (["--board", "9x6", "--square", "0.03"], {"right": "small.png"},
         "Invalid value for '?RIGHT'?: the image is 320x240, the calibration 640x480"),
        (["--board", "9x6", "--square", "0.03"], {"calib": "notes.txt"},
         "Invalid value for '?--calib'?: calibration .*notes.txt: expected a mapping"),
        (["--points", "5,5", "100,100"], {"left": "blank.png", "right": "blank.png"},
         "expected it at least 12 px inside the image"),
        (["--points", "300,200", "320,220"], {"left": "blank.png", "right": "blank.png"},
         "no right-image match: .*; give the points' right-image matches with --right-points"),
    ],
)
def test_bad_input_is_a_usage_error(kit: dict[str, str], args: list[str],
                                    files: dict[str, str], error: str) -> None:
    names = {"left": "left.png", "right": "right.png", "calib": "calib.yaml", **files}
    code, out = run(kit, *args, **names)
    assert code == 2, out
    flat = " ".join(out.split())  # click wraps long messages
    assert re.search(error, flat), flat


def test_measure_is_in_the_command_list() -> None:
    out = CliRunner().invoke(main, ["--help"]).output
    assert "measure" in out

