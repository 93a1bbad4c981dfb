"""Every calibration file of the kit loads, or is refused with a reason, and the
rectification trapflow computes agrees with the one the file carries.

Files: 07_ros_calib_yamls (ROS camera_info, Kalibr camchains and target) and
01b/reference (a ROS camera_info pair and its oST text, OpenCV fisheye FileStorage).
The references are the files' own R1/R2 (ROS `rectification_matrix`, OpenCV's R1/R2)
and their rectified baseline (P2[0][3] / P2[0][0]), read here with PyYAML and
cv2.FileStorage, independently of trapflow's readers.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from trapflow.calibration.formats import load_calibration
from trapflow.calibration.model import StereoCalibration
from trapflow.errors import ConfigError

from .conftest import kit_path

ROS = "07_ros_calib_yamls"
FISH = "01b_stereo_fisheye_checkerboard_ros_image_pipeline/reference"

# (kit file, expected: "pair" = loads as a stereo pair, else a ConfigError fragment)
CASES = [
    (f"{ROS}/ros_stereo_left.yaml", "pair"),
    (f"{ROS}/ros_stereo_right.yaml", "pair"),
    (f"{ROS}/ros_camera_info_manager_test_calibration.yaml", "a stereo pair is needed"),
    (f"{ROS}/kalibr_camchain-camera.yaml", r"one camera \(cam0 only\)"),
    (f"{ROS}/kalibr_camchain-imucam-camera_imu.yaml", r"one camera \(cam0 only\)"),
    (f"{ROS}/kalibr_april_6x6_80x80cm.yaml", "format not recognised"),
    (f"{FISH}/ros_camera_calibration_left.yaml", "pair"),
    (f"{FISH}/ros_camera_calibration_right.yaml", "pair"),
    (f"{FISH}/ros_camera_calibration_ost.txt", "pair"),
    (f"{FISH}/opencv_fisheye_calibrate_cam_stereo.yml", "no image size in the file"),
]


def test_every_kit_calibration_file_is_covered(realdata: Path) -> None:
    """A file added to the kit's calibration folders gets a row in CASES."""
    present = {f"{d}/{p.name}" for d in (ROS, FISH)
               for p in kit_path(realdata, d).iterdir() if p.suffix in (".yaml", ".yml", ".txt")
               and not p.name.startswith(("verify", "README"))}
    assert present == {name for name, _ in CASES}


@pytest.mark.parametrize(("name", "expected"), CASES)
def test_kit_file_loads_or_says_why(realdata: Path, name: str, expected: str) -> None:
    path = kit_path(realdata, *name.split("/"))
    if expected != "pair":
        with pytest.raises(ConfigError, match=expected) as err:
            load_calibration(path)
        assert str(path) in str(err.value) and "formats understood" in str(err.value)
        return
    calib = load_calibration(path)
    assert calib.model == "fisheye"  # the kit's ROS files: plumb_bob with 4 coefficients
    assert calib.size == (800, 503)


def camera_info(path: Path) -> dict[str, np.ndarray]:
    doc = yaml.safe_load(path.read_text())
    return {"R": np.reshape(doc["rectification_matrix"]["data"], (3, 3)),
            "P": np.reshape(doc["projection_matrix"]["data"], (3, 4)),
            "K": np.reshape(doc["camera_matrix"]["data"], (3, 3))}


def assert_rectification_agrees(calib: StereoCalibration, r1: np.ndarray, r2: np.ndarray,
                                p2: np.ndarray, atol: float) -> None:
    """Same rectifying rotations; same rectified baseline; rows shared by both eyes."""
    np.testing.assert_allclose(calib.arr("R1"), r1, atol=atol)
    np.testing.assert_allclose(calib.arr("R2"), r2, atol=atol)
    p1c, p2c = calib.arr("P1"), calib.arr("P2")
    assert -p2c[0, 3] / p2c[0, 0] == pytest.approx(-p2[0, 3] / p2[0, 0], rel=1e-4)
    assert p1c[1, 2] == p2c[1, 2] and p1c[1, 1] == p2c[1, 1] and p1c[0, 0] == p2c[0, 0]
    assert calib.rig().baseline_m == pytest.approx(-p2[0, 3] / p2[0, 0], rel=1e-4)


@pytest.mark.parametrize("folder", [ROS, FISH])
def test_ros_pair_rectification_reproduces_the_files(realdata: Path, folder: str) -> None:
    """R1/R2 computed from K/D and the extrinsics reproduce the files' rectification_matrix
    to their 6 printed decimals, and the baseline their projection_matrix gives."""
    d = kit_path(realdata, *folder.split("/"))
    left_name = "ros_stereo_left.yaml" if folder == ROS else "ros_camera_calibration_left.yaml"
    left = camera_info(d / left_name)
    right = camera_info(d / left_name.replace("left", "right"))
    spec = f"{d / left_name},{d / left_name.replace('left', 'right')}"
    calib = load_calibration(spec)
    assert_rectification_agrees(calib, left["R"], right["R"], right["P"], atol=2e-6)
    np.testing.assert_allclose(calib.arr("K1"), left["K"])
    # The same pair given as a folder, as LEFT only and as RIGHT only: the same calibration.
    for other in (str(d / left_name), str(d / left_name.replace("left", "right"))):
        assert load_calibration(other) == calib
    if folder == FISH:
        assert load_calibration(d) == calib
        assert load_calibration(d / "ros_camera_calibration_ost.txt") == calib


def test_opencv_fisheye_yml_rectification_reproduces_the_file(realdata: Path) -> None:
    """cv::fisheye::stereoCalibrate's file: R1/R2 recomputed from K/D/R/T equal the file's;
    the baseline equals P2's. (Its P1 focal length, 235 px with cx 125 on an 800 px image,
    is not reproduced: see docs/calibration.md.)"""
    path = kit_path(realdata, *FISH.split("/"), "opencv_fisheye_calibrate_cam_stereo.yml")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    ref = {k: fs.getNode(k).mat() for k in ("K1", "R1", "R2", "P2")}
    fs.release()
    calib = load_calibration(path, image_size=(800, 503))
    assert calib.model == "fisheye"
    np.testing.assert_allclose(calib.arr("K1"), ref["K1"])
    assert_rectification_agrees(calib, ref["R1"], ref["R2"], ref["P2"], atol=1e-9)
