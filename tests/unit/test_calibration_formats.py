"""Calibration formats: each written here by an independent writer (PyYAML by hand,
cv2.FileStorage) from one known rig, read by load_calibration, and compared with OpenCV's
own cv2.stereoRectify / cv2.fisheye.stereoRectify of the same numbers; then a table of
files that must be refused with the file, the field and the fix named."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from trapflow.calibration.formats import load_calibration, write_camera_info
from trapflow.calibration.model import StereoCalibration
from trapflow.errors import ConfigError
from trapflow.sources.rectify import Rectifier

SIZE = (640, 480)
K1 = np.array([[520.0, 0, 321.5], [0, 519.0, 242.0], [0, 0, 1]])
K2 = np.array([[522.0, 0, 318.0], [0, 521.5, 238.5], [0, 0, 1]])
D1 = np.array([-0.21, 0.05, 0.001, -0.0005, 0.01])
D2 = np.array([-0.20, 0.04, -0.0008, 0.0003, 0.0])
R, _ = cv2.Rodrigues(np.array([0.004, -0.012, 0.002]))
T = np.array([-0.12, 0.0011, 0.0023])
FD1 = np.array([-0.05, 0.008, -0.007, 0.0016])
FD2 = np.array([-0.035, -0.02, 0.0117, -0.0031])


def opencv_rectify() -> tuple[np.ndarray, ...]:
    r1, r2, p1, p2, q, _, _ = cv2.stereoRectify(K1, D1, K2, D2, SIZE, R, T.reshape(3, 1),
                                                flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
    return r1, r2, p1, p2, q


def assert_is_the_rig(calib: StereoCalibration, atol: float = 1e-9) -> None:
    """K/D/R/T as written and the rectification OpenCV's stereoRectify gives for them."""
    assert calib.model == "pinhole" and calib.size == SIZE
    np.testing.assert_allclose(calib.arr("K1"), K1, atol=atol)
    np.testing.assert_allclose(calib.arr("K2"), K2, atol=atol)
    np.testing.assert_allclose(calib.arr("D1")[:4], D1[:4], atol=atol)
    np.testing.assert_allclose(calib.arr("R"), R, atol=atol)
    np.testing.assert_allclose(calib.arr("T"), T, atol=atol)
    for name, want in zip(("R1", "R2", "P1", "P2", "Q"), opencv_rectify(), strict=True):
        np.testing.assert_allclose(calib.arr(name), want, atol=max(atol, 1e-9) * 1e3,
                                   err_msg=name)
    assert calib.baseline_m == pytest.approx(float(np.linalg.norm(T)))


def flat(a: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(a).ravel()]


def test_plain_k_d_r_t_yaml_is_rectified_by_trapflow(tmp_path: Path) -> None:
    p = tmp_path / "plain.yaml"
    p.write_text(yaml.safe_dump({
        "image_width": SIZE[0], "image_height": SIZE[1],
        "K1": K1.tolist(), "D1": flat(D1), "K2": K2.tolist(), "D2": flat(D2),
        "R": R.tolist(), "T": flat(T)}))
    assert_is_the_rig(load_calibration(p))


def test_kalibr_stereo_camchain(tmp_path: Path) -> None:
    def cam(k: np.ndarray, d: np.ndarray) -> dict[str, object]:
        return {"camera_model": "pinhole",
                "intrinsics": flat(np.array([k[0, 0], k[1, 1], k[0, 2], k[1, 2]])),
                "distortion_model": "radtan", "distortion_coeffs": flat(d[:4]),
                "resolution": list(SIZE), "rostopic": "/cam/image_raw"}

    tf = np.eye(4)
    tf[:3, :3], tf[:3, 3] = R, T
    chain = {"cam0": cam(K1, D1), "cam1": {**cam(K2, D2), "T_cn_cnm1": tf.tolist()}}
    (tmp_path / "camchain.yaml").write_text(yaml.safe_dump(chain))
    calib = load_calibration(tmp_path / "camchain.yaml")
    np.testing.assert_allclose(calib.arr("D1"), np.r_[D1[:4], 0.0])
    np.testing.assert_allclose(calib.arr("R"), R)
    np.testing.assert_allclose(calib.arr("T"), T)
    r1, r2, p1, p2, _, _, _ = cv2.stereoRectify(K1, np.r_[D1[:4], 0], K2, np.r_[D2[:4], 0],
                                                SIZE, R, T.reshape(3, 1),
                                                flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
    np.testing.assert_allclose(calib.arr("P1"), p1, atol=1e-6)
    np.testing.assert_allclose(calib.arr("R2"), r2, atol=1e-9)


def write_fs(path: Path, fields: dict[str, object]) -> None:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for key, value in fields.items():
        fs.write(key, value)
    fs.release()


@pytest.mark.parametrize("suffix", [".yml", ".xml"])
def test_opencv_filestorage_stereo_file(tmp_path: Path, suffix: str) -> None:
    r1, r2, p1, p2, q = opencv_rectify()
    p = tmp_path / f"stereo{suffix}"
    write_fs(p, {"image_width": SIZE[0], "image_height": SIZE[1], "K1": K1, "D1": D1,
                 "K2": K2, "D2": D2, "R": R, "T": T, "R1": r1, "R2": r2, "P1": p1,
                 "P2": p2, "Q": q})
    assert "opencv-matrix" in p.read_text()
    assert_is_the_rig(load_calibration(p))


def test_stereo_calib_cpp_intrinsics_and_extrinsics(tmp_path: Path) -> None:
    """stereo_calib.cpp writes M1 D1 M2 D2 to intrinsics.yml and R T R1 R2 P1 P2 Q to
    extrinsics.yml, with no image size: given as a pair, a folder or either file."""
    r1, r2, p1, p2, q = opencv_rectify()
    write_fs(tmp_path / "intrinsics.yml", {"M1": K1, "D1": D1, "M2": K2, "D2": D2})
    write_fs(tmp_path / "extrinsics.yml", {"R": R, "T": T, "R1": r1, "R2": r2, "P1": p1,
                                           "P2": p2, "Q": q})
    pair = f"{tmp_path / 'intrinsics.yml'},{tmp_path / 'extrinsics.yml'}"
    calib = load_calibration(pair, image_size=SIZE)
    assert_is_the_rig(calib)
    for spec in (tmp_path, tmp_path / "intrinsics.yml", tmp_path / "extrinsics.yml"):
        assert load_calibration(spec, image_size=SIZE) == calib
    with pytest.raises(ConfigError, match="no image size in the file"):
        load_calibration(pair)


def ros_camera_info(path: Path, k: np.ndarray, d: np.ndarray, r: np.ndarray, p: np.ndarray,
                    model: str = "plumb_bob") -> None:
    """A camera_info YAML as ROS camera_calibration writes it."""
    doc = {"image_width": SIZE[0], "image_height": SIZE[1], "camera_name": path.stem,
           "camera_matrix": {"rows": 3, "cols": 3, "data": flat(k)},
           "distortion_model": model,
           "distortion_coefficients": {"rows": 1, "cols": len(d), "data": flat(d)},
           "rectification_matrix": {"rows": 3, "cols": 3, "data": flat(r)},
           "projection_matrix": {"rows": 3, "cols": 4, "data": flat(p)}}
    path.write_text(yaml.safe_dump(doc, sort_keys=False))


def test_ros_camera_info_pair_gives_back_the_extrinsics(tmp_path: Path) -> None:
    r1, r2, p1, p2, _ = opencv_rectify()
    ros_camera_info(tmp_path / "left.yaml", K1, D1, r1, p1)
    ros_camera_info(tmp_path / "right.yaml", K2, D2, r2, p2)
    calib = load_calibration(tmp_path / "left.yaml")
    assert_is_the_rig(calib, atol=1e-7)
    for spec in (tmp_path, tmp_path / "right.yaml",
                 f"{tmp_path / 'right.yaml'},{tmp_path / 'left.yaml'}"):
        assert load_calibration(spec) == calib


def test_camera_info_writer_round_trip(tmp_path: Path) -> None:
    """trapflow's camera_info pair is what ROS expects (checked with PyYAML) and reads back."""
    calib = load_calibration_from_numbers(tmp_path)
    write_camera_info(calib, tmp_path / "left.yaml", tmp_path / "right.yaml")
    right = yaml.safe_load((tmp_path / "right.yaml").read_text())
    assert right["distortion_model"] == "plumb_bob"
    assert right["distortion_coefficients"]["cols"] == 5
    assert right["projection_matrix"]["data"][3] == pytest.approx(
        -calib.arr("P2")[0, 0] * np.linalg.norm(T), rel=1e-3)
    back = load_calibration(tmp_path / "left.yaml")
    for name in ("K1", "D1", "K2", "D2", "R", "T", "R1", "R2", "P1", "P2", "Q"):
        np.testing.assert_allclose(back.arr(name), calib.arr(name), atol=1e-7, err_msg=name)


def load_calibration_from_numbers(folder: Path) -> StereoCalibration:
    p = folder / "plain.yaml"
    p.write_text(yaml.safe_dump({
        "image_width": SIZE[0], "image_height": SIZE[1], "K1": K1.tolist(), "D1": flat(D1),
        "K2": K2.tolist(), "D2": flat(D2), "R": R.tolist(), "T": flat(T)}))
    return load_calibration(p)


def test_fisheye_plain_yaml_rectifies_with_fisheye_maps(tmp_path: Path) -> None:
    """A fisheye's rotations are OpenCV's; its maps are cv2.fisheye's for the same P."""
    p = tmp_path / "fish.yaml"
    p.write_text(yaml.safe_dump({
        "model": "fisheye", "image_width": SIZE[0], "image_height": SIZE[1],
        "K1": K1.tolist(), "D1": flat(FD1), "K2": K2.tolist(), "D2": flat(FD2),
        "R": R.tolist(), "T": flat(T)}))
    calib = load_calibration(p)
    assert calib.model == "fisheye"
    r1, r2, _, _, _ = cv2.fisheye.stereoRectify(K1, FD1, K2, FD2, SIZE, R, T.reshape(3, 1),
                                                cv2.CALIB_ZERO_DISPARITY)
    np.testing.assert_allclose(calib.arr("R1"), r1, atol=1e-12)
    np.testing.assert_allclose(calib.arr("R2"), r2, atol=1e-12)
    p1 = calib.arr("P1")
    assert p1[0, 0] == min(K1[0, 0], K1[1, 1], K2[0, 0], K2[1, 1]) == p1[1, 1]
    # The rectifier's left map is cv2.fisheye.initUndistortRectifyMap's, not the pinhole one.
    img = np.random.default_rng(1).integers(0, 255, (SIZE[1], SIZE[0]), np.uint8)
    got, _ = Rectifier(calib).apply(img, img)
    m1, m2 = cv2.fisheye.initUndistortRectifyMap(K1, FD1, r1, p1, SIZE, cv2.CV_16SC2)
    np.testing.assert_array_equal(got, cv2.remap(img, m1, m2, cv2.INTER_LINEAR))
    m1p, m2p = cv2.initUndistortRectifyMap(K1, FD1, r1, p1, SIZE, cv2.CV_16SC2)
    assert np.abs(got.astype(int) - cv2.remap(img, m1p, m2p, cv2.INTER_LINEAR)).mean() > 5


def ros_doc(**override: object) -> str:
    doc: dict[str, object] = {
        "image_width": 640, "image_height": 480, "camera_name": "left",
        "camera_matrix": {"rows": 3, "cols": 3, "data": flat(K1)},
        "distortion_model": "plumb_bob",
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": flat(D1)},
        "rectification_matrix": {"rows": 3, "cols": 3, "data": flat(np.eye(3))},
        "projection_matrix": {"rows": 3, "cols": 4,
                              "data": [500, 0, 320, 0, 0, 500, 240, 0, 0, 0, 1, 0]}}
    doc.update(override)
    return yaml.safe_dump({k: v for k, v in doc.items() if v is not None})


RIGHT_P = {"rows": 3, "cols": 4, "data": [500, 0, 320, -60, 0, 500, 240, 0, 0, 0, 1, 0]}


def plain(**override: object) -> str:
    doc: dict[str, object] = {"image_width": 640, "image_height": 480, "K1": K1.tolist(),
                              "D1": flat(D1), "K2": K2.tolist(), "D2": flat(D2),
                              "R": R.tolist(), "T": flat(T)}
    doc.update(override)
    return yaml.safe_dump({k: v for k, v in doc.items() if v is not None})


def kalibr(**cam1: object) -> str:
    base = {"camera_model": "pinhole", "intrinsics": [520, 519, 320, 240],
            "distortion_model": "radtan", "distortion_coeffs": [0, 0, 0, 0],
            "resolution": [640, 480]}
    tf = np.eye(4)
    tf[0, 3] = -0.1
    second = {**base, "T_cn_cnm1": tf.tolist(), **cam1}
    return yaml.safe_dump({"cam0": base, "cam1": {k: v for k, v in second.items()
                                                  if v is not None}})


# (files to write: name -> text, spec to load (names joined by ','), error fragment)
REJECTED = [
    ({"left.yaml": ros_doc(), "right.yaml": ros_doc(image_width=800,
                                                     projection_matrix=RIGHT_P)},
     "left.yaml,right.yaml", "image sizes differ"),
    ({"left.yaml": ros_doc(projection_matrix=RIGHT_P),
      "right.yaml": ros_doc(projection_matrix=RIGHT_P)},
     "left.yaml,right.yaml", r"expected P\[0\]\[3\] = 0 in the left file"),
    ({"left.yaml": ros_doc(distortion_model="fov"), "right.yaml": ros_doc()},
     "left.yaml,right.yaml", "distortion_model: expected one of plumb_bob"),
    ({"left.yaml": ros_doc(projection_matrix=None), "right.yaml": ros_doc()},
     "left.yaml,right.yaml", "missing field 'projection_matrix'"),
    ({"cam.yaml": ros_doc()}, "cam.yaml", "a stereo pair is needed"),
    ({"left.yaml": ros_doc()}, "left.yaml", "a stereo pair is needed"),
    ({"a.yaml": plain(), "b.yaml": plain(), "c.yaml": plain()}, "a.yaml,b.yaml,c.yaml",
     "expected LEFT,RIGHT"),
    ({"chain.yaml": kalibr(T_cn_cnm1=None)}, "chain.yaml", "missing field 'T_cn_cnm1'"),
    ({"chain.yaml": kalibr(camera_model="omni")}, "chain.yaml", "expected pinhole, got 'omni'"),
    ({"chain.yaml": kalibr(distortion_model="fov")}, "chain.yaml",
     "cam1.distortion_model: expected one of radtan"),
    ({"chain.yaml": kalibr(resolution=[800, 600])}, "chain.yaml", "cam0 and cam1 differ"),
    ({"p.yaml": plain(image_width=None)}, "p.yaml", "needs image_width"),
    ({"p.yaml": plain(K1=[[1, 0], [0, 1]])}, "p.yaml", r"field K1: expected shape \(3, 3\)"),
    ({"p.yaml": plain(model="omni")}, "p.yaml", "model: expected one of pinhole, fisheye"),
    ({"p.yaml": plain(R=(2 * np.eye(3)).tolist())}, "p.yaml", r"expected a rotation"),
    ({"p.yaml": plain(model="fisheye")}, "p.yaml", "a fisheye lens has 4 coefficients"),
    ({"p.yaml": plain(T=[1, 2])}, "p.yaml", "field T: expected 3 numbers"),
    ({"x.yaml": "foo: 1\n"}, "x.yaml", "format not recognised"),
]


@pytest.mark.parametrize(("files", "spec", "error"), REJECTED)
def test_rejected_with_file_field_and_formats(tmp_path: Path, files: dict[str, str],
                                              spec: str, error: str) -> None:
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    full = ",".join(str(tmp_path / n) for n in spec.split(","))
    with pytest.raises(ConfigError, match=error) as err:
        load_calibration(full)
    assert str(tmp_path) in str(err.value)


@pytest.mark.parametrize(
    ("fields", "error"),
    [
        ({"cameraMatrix": np.eye(3), "distCoeffs": np.zeros(5), "image_width": 640,
          "image_height": 480}, "a single camera's calibration"),
        ({"M1": K1, "D1": D1, "M2": K2, "D2": D2}, "without R and T"),
        ({"R": R, "T": T}, "without K1/M1"),
        ({"K1": K1, "D1": D1, "K2": K2, "D2": D2, "R": R, "T": T, "R1": np.eye(3),
          "R2": np.eye(3), "image_width": 640, "image_height": 480},
         "the file contradicts itself"),
    ],
)
def test_opencv_files_rejected(tmp_path: Path, fields: dict[str, object], error: str) -> None:
    p = tmp_path / "cv.yml"
    write_fs(p, fields)
    with pytest.raises(ConfigError, match=error) as err:
        load_calibration(p)
    assert str(p) in str(err.value) and "formats understood" in str(err.value)


def test_empty_folder(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no readable calibration file"):
        load_calibration(tmp_path)
