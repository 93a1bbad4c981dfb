"""Stereo calibration against a known rig, on checkerboard views rendered here."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from trapflow.calibration.calibrate import CalibrationError, calibrate_stereo, expand, parse_pattern
from trapflow.calibration.camera import StereoRig
from trapflow.calibration.formats import load_calibration
from trapflow.calibration.model import save_calibration
from trapflow.cli.sources import calibrate
from trapflow.errors import ConfigError
from trapflow.sources.rectify import Rectifier
from trapflow.testing.checkerboard import render_pair

RIG = StereoRig.from_fov(640, 480, 65.0, 0.12)
PATTERN = (9, 6)
SQUARE = 0.025


def write_views(folder: Path, n_good: int = 10, n_bad: int = 1) -> None:
    rng = np.random.default_rng(7)
    (folder / "L").mkdir(parents=True)
    (folder / "R").mkdir(parents=True)
    for i in range(n_good + n_bad):
        rvec = rng.uniform(-0.35, 0.35, 3)
        tvec = np.array([rng.uniform(-0.16, 0.0), rng.uniform(-0.1, 0.0), rng.uniform(0.55, 0.8)])
        if i >= n_good:
            tvec = np.array([2.0, 0.0, 0.6])  # board outside both views: must be rejected
        left, right = render_pair(RIG, PATTERN, SQUARE, rvec, tvec)
        cv2.imwrite(str(folder / "L" / f"v{i:02d}.png"), left)
        cv2.imwrite(str(folder / "R" / f"v{i:02d}.png"), right)


@pytest.mark.timeout(90)
def test_recovers_known_rig_and_round_trips_yaml(tmp_path: Path) -> None:
    write_views(tmp_path)
    report = calibrate_stereo(expand(str(tmp_path / "L" / "*.png")),
                              expand(str(tmp_path / "R" / "*.png")), PATTERN, SQUARE)
    c = report.calibration
    assert report.rejected == ["v10.png|v10.png"] and len(report.used) == 10
    assert report.rms_px < 0.5
    assert c.baseline_m == pytest.approx(0.12, rel=0.02)
    assert c.arr("K1")[0, 0] == pytest.approx(RIG.fx, rel=0.02)
    assert c.arr("K2")[1, 1] == pytest.approx(RIG.fy, rel=0.02)
    assert c.arr("T")[0] == pytest.approx(-0.12, rel=0.02)
    assert np.allclose(c.arr("R"), np.eye(3), atol=0.01)

    save_calibration(c, tmp_path / "calib.yaml")
    back = load_calibration(tmp_path / "calib.yaml")
    assert back == c
    rig = back.rig()
    assert rig.baseline_m == pytest.approx(0.12, rel=0.02)
    assert rig.fx == pytest.approx(RIG.fx, rel=0.05)
    # Rectified views of a fronto-parallel board: corners lie on the same rows in both eyes.
    left, right = render_pair(RIG, PATTERN, SQUARE, np.zeros(3), np.array([-0.1, -0.07, 0.7]))
    rl, rr = Rectifier(back).apply(cv2.cvtColor(left, cv2.COLOR_GRAY2BGR),
                                   cv2.cvtColor(right, cv2.COLOR_GRAY2BGR))
    fl, cl = cv2.findChessboardCorners(cv2.cvtColor(rl, cv2.COLOR_BGR2GRAY), PATTERN)
    fr, cr = cv2.findChessboardCorners(cv2.cvtColor(rr, cv2.COLOR_BGR2GRAY), PATTERN)
    assert fl and fr
    assert np.abs(cl.reshape(-1, 2)[:, 1] - cr.reshape(-1, 2)[:, 1]).max() < 1.0


def test_no_corners_anywhere_is_one_clear_error(tmp_path: Path) -> None:
    write_views(tmp_path, n_good=0, n_bad=3)
    with pytest.raises(CalibrationError, match="found in both images of 0 of 3 pairs"):
        calibrate_stereo(expand(str(tmp_path / "L" / "*")), expand(str(tmp_path / "R" / "*")),
                         PATTERN, SQUARE)


@pytest.mark.parametrize(
    ("left", "right", "error"),
    [
        ([], [], "no images"),
        ([Path("a.png")], [], "no images"),
        ([Path("a.png"), Path("b.png")], [Path("c.png")], "2 left and 1 right"),
        ([Path("missing.png")], [Path("missing2.png")], "cannot read image"),
    ],
)
def test_bad_image_lists(left: list[Path], right: list[Path], error: str) -> None:
    with pytest.raises(CalibrationError, match=error):
        calibrate_stereo(left, right, PATTERN, SQUARE)


@pytest.mark.parametrize(
    ("text", "expected", "error"),
    [("9x6", (9, 6), None), ("7X5", (7, 5), None), ("9", None, "expected COLSxROWS"),
     ("1x6", None, "expected COLSxROWS"), ("ax6", None, "expected COLSxROWS")],
)
def test_parse_pattern(text: str, expected: tuple[int, int] | None, error: str | None) -> None:
    if error is None:
        assert parse_pattern(text) == expected
    else:
        with pytest.raises(ValueError, match=error):
            parse_pattern(text)


@pytest.mark.parametrize(
    ("content", "error"),
    [
        ("image_width: 640\n", "missing required field `image_height`"),
        ("[1, 2]", "expected a mapping"),
        ("a: [", "not valid YAML"),
    ],
)
def test_load_calibration_names_the_problem(tmp_path: Path, content: str, error: str) -> None:
    (tmp_path / "c.yaml").write_text(content)
    with pytest.raises(ConfigError, match=error):
        load_calibration(tmp_path / "c.yaml")


def test_load_calibration_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read calibration"):
        load_calibration(tmp_path / "nope.yaml")


@pytest.mark.timeout(90)
def test_calibrate_command_writes_a_camera_info_pair_that_reads_back(tmp_path: Path) -> None:
    """`--camera-info DIR` writes left.yaml and right.yaml as ROS camera_info; read back as a
    pair they give the calibration the command wrote (rectification recomputed the same)."""
    write_views(tmp_path, n_good=8, n_bad=0)
    out, info = tmp_path / "calib.yaml", tmp_path / "ros"
    res = CliRunner().invoke(calibrate, [str(tmp_path / "L" / "*.png"),
                                         str(tmp_path / "R" / "*.png"), "--square", "0.025",
                                         "-o", str(out), "--camera-info", str(info)])
    assert res.exit_code == 0, res.output
    assert f"written: {info / 'left.yaml'}, {info / 'right.yaml'}" in res.output
    ours, ros = load_calibration(out), load_calibration(info)
    left = yaml.safe_load((info / "left.yaml").read_text())
    assert left["distortion_model"] == "plumb_bob" and left["image_width"] == 640
    for name in ("K1", "D1", "K2", "D2", "R", "T", "R1", "R2", "P1", "P2", "Q"):
        np.testing.assert_allclose(ros.arr(name), ours.arr(name), atol=1e-7, err_msg=name)


def test_calibrate_command_rejects_an_unknown_model() -> None:
    res = CliRunner().invoke(calibrate, ["L*.png", "R*.png", "--model", "omni"])
    assert res.exit_code == 2 and "'omni' is not one of" in res.output


def test_calibrate_stereo_rejects_an_unknown_model(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="model: expected one of pinhole, rational"):
        calibrate_stereo([tmp_path / "a.png"], [tmp_path / "b.png"], PATTERN, SQUARE, "omni")
