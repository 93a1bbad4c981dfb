"""The run's rig is decided in one place: the order of the sources of truth, the id, rig files."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from tests.builders import kitti_calib, rectified_calibration
from trapflow.calibration import rig_files
from trapflow.calibration.camera import StereoRig
from trapflow.calibration.model import save_calibration
from trapflow.config import schema as config
from trapflow.errors import ConfigError
from trapflow.sources import rig
from trapflow.sources.base import Geometry

CALIB_TXT = StereoRig(width=752, height=480, fx=436.0, fy=435.0, cx=370.5, cy=235.2,
                      baseline_m=0.11)


def test_id_is_a_hash_of_the_numbers() -> None:
    """The documented recipe, re-done here: BLAKE2b-32 of `WxH fx fy cx cy baseline`."""
    text = "752x480 436.000 435.000 370.500 235.200 0.110000"
    assert CALIB_TXT.id == hashlib.blake2b(text.encode(), digest_size=4).hexdigest()
    assert len(CALIB_TXT.id) == 8


@pytest.mark.parametrize(
    ("change", "same"),
    [
        ({"fx": 436.0 + 1e-6}, True),  # parsing noise
        ({"baseline_m": 0.11 + 1e-9}, True),
        ({"fx": 436.01}, False),
        ({"cy": 235.3}, False),
        ({"baseline_m": 0.111}, False),
        ({"width": 753}, False),
    ],
)
def test_id_changes_with_the_calibration_only(change: dict[str, float], same: bool) -> None:
    other = StereoRig(**{**{f: getattr(CALIB_TXT, f) for f in CALIB_TXT.__struct_fields__},
                         **change})
    assert (other.id == CALIB_TXT.id) is same


def cfg_with(calibration: str | None = None, size: tuple[int, int] = (1280, 720)) -> config.Config:
    return config.from_data({"source": {"width": size[0], "height": size[1]},
                             "rig": {"calibration": calibration, "hfov_deg": 90.0,
                                     "baseline_m": 0.2}})


def write_calibration(path: Path, r: StereoRig) -> str:
    save_calibration(rectified_calibration(r), path)
    return str(path)


def test_resolve_order(tmp_path: Path) -> None:
    """A calibration file, then the source's own rig, then its frame size with the configured
    field of view, then the configured size."""
    file_rig = StereoRig.from_fov(752, 480, 60.0, 0.15)
    path = write_calibration(tmp_path / "c.yaml", file_rig)
    own = Geometry(size=(752, 480), rig=CALIB_TXT, origin="calib.txt", where="images in D")
    sized = Geometry(size=(752, 480), where="images in D")

    got = rig.resolve(cfg_with(path), own)
    assert got.rig == file_rig and got.origin == f"calibration file {path}"
    got = rig.resolve(cfg_with(), own)
    assert got.rig == CALIB_TXT and got.origin == "calib.txt"
    got = rig.resolve(cfg_with(), sized)
    assert got.rig == StereoRig.from_fov(752, 480, 90.0, 0.2)
    assert got.origin.startswith("images in D's frame size")
    got = rig.resolve(cfg_with(size=(640, 360)), Geometry())
    assert got.rig == StereoRig.from_fov(640, 360, 90.0, 0.2)


def test_source_options_rectify_names_the_calibration(tmp_path: Path) -> None:
    path = write_calibration(tmp_path / "c.yaml", CALIB_TXT)
    cfg = config.from_data({"source": {"options": {"rectify": path}}})
    assert rig.resolve(cfg, Geometry()).rig == CALIB_TXT


@pytest.mark.parametrize(("in_rig", "in_options", "applies"), [
    (None, None, None),  # no file: the source or the config decide the rig
    ("a.yaml", None, "a.yaml"),  # rig.calibration
    (None, "b.yaml", "b.yaml"),  # source.options.rectify
    ("a.yaml", "b.yaml", "b.yaml"),  # both: the source's option wins
])
def test_which_calibration_file_applies(tmp_path: Path, in_rig: str | None,
                                        in_options: str | None, applies: str | None) -> None:
    """Regression: the supervisor (the run's rig) and capture (its rectification) each
    decided which file applied; both now ask run_calibration, which reads that file."""
    paths = {name: write_calibration(tmp_path / name, StereoRig.from_fov(
        320, 240, 60.0 + i, 0.1)) for i, name in enumerate(("a.yaml", "b.yaml"))}
    data: dict[str, object] = {"rig": {"calibration": paths[in_rig] if in_rig else None}}
    if in_options:
        data["source"] = {"options": {"rectify": paths[in_options]}}
    cfg = config.from_data(data)
    assert rig.calibration_path(cfg) == (paths[applies] if applies else None)
    calib = rig.run_calibration(cfg)
    if applies is None:
        assert calib is None
    else:
        assert calib is not None
        assert calib.rig() == rig.resolve(cfg, Geometry()).rig == StereoRig.from_fov(
            320, 240, 60.0 + ("a.yaml", "b.yaml").index(applies), 0.1)


def test_calibration_contradicting_the_frames_fails_in_one_line(tmp_path: Path) -> None:
    path = write_calibration(tmp_path / "c.yaml", StereoRig.from_fov(1280, 720, 70.0, 0.12))
    with pytest.raises(ConfigError) as err:
        rig.resolve(cfg_with(path), Geometry(size=(752, 480), where="images in D"))
    msg = str(err.value)
    assert "\n" not in msg
    assert "frames of images in D are 752x480" in msg and "is 1280x720" in msg
    assert "trapflow calibrate" in msg


def test_describe_reads_a_kitti_folder_without_opening_it(tmp_path: Path) -> None:
    import cv2
    import numpy as np

    for side in ("image_0", "image_1"):
        (tmp_path / side).mkdir()
        cv2.imwrite(str(tmp_path / side / "000000.png"), np.zeros((480, 752), np.uint8))
    (tmp_path / "calib.txt").write_text(kitti_calib(CALIB_TXT))
    cfg = config.from_data({"source": {"kind": "images", "uri": str(tmp_path)}})
    got = rig.describe(cfg)
    assert got.rig.id == CALIB_TXT.id and got.origin == str(tmp_path / "calib.txt")
    (tmp_path / "calib.txt").unlink()
    got = rig.describe(cfg)
    assert got.rig == StereoRig.from_fov(752, 480, 70.0, 0.12)


@pytest.mark.parametrize(
    ("name", "text", "error"),
    [
        ("calib.txt", "P0: " + "1 " * 12 + "\n", "missing field P1"),
        ("calib.txt", "P0: 1 2\nP1: 1 2\n", "P0 expected 12 numbers"),
        ("calib.txt", "P0: " + "1 " * 12 + "\nP1: " + "1 " * 12 + "\n",
         "positive baseline -P1"),
        ("calib.txt", "P0: 1 x 3\n", "row 'P0' expected numbers"),
        ("c.yaml", "fx: 500\nfy: 500\ncx: 320\ncy: 240\n", "missing field 'baseline_m'"),
        ("c.yaml", "fx: 500\nfy: -1\ncx: 1\ncy: 1\nbaseline_m: 1\n", "fy expected a positive"),
        ("c.yaml", "fx: 500\nfy: true\ncx: 1\ncy: 1\nbaseline_m: 1\n", "fy expected a positive"),
        ("c.yaml", "- 1\n- 2\n", "expected a mapping"),
    ],
)
def test_rig_files_reject_bad_input(tmp_path: Path, name: str, text: str, error: str) -> None:
    (tmp_path / name).write_text(text)
    with pytest.raises(ConfigError, match=error):
        rig_files.read_rig_file(tmp_path / name, (640, 480))


def test_rig_files(tmp_path: Path) -> None:
    (tmp_path / "calib.txt").write_text(kitti_calib(CALIB_TXT))
    assert rig_files.read_rig_file(tmp_path / "calib.txt", (752, 480)).id == CALIB_TXT.id
    (tmp_path / "c.yaml").write_text("fx: 436\nfy: 435\ncx: 370.5\ncy: 235.2\nbaseline_m: 0.11\n")
    assert rig_files.read_rig_file(tmp_path / "c.yaml", (752, 480)) == CALIB_TXT
    path = write_calibration(tmp_path / "full.yaml", CALIB_TXT)
    assert rig_files.read_rig_file(Path(path), (1, 1)) == CALIB_TXT  # its own image size wins


def test_describe_skips_an_unreadable_first_image(tmp_path: Path) -> None:
    """A 0-byte first file does not stop the start: the frame size comes from the next one."""
    import cv2
    import numpy as np

    for side in ("left", "right"):
        (tmp_path / side).mkdir()
        (tmp_path / side / "000.png").write_bytes(b"")
        cv2.imwrite(str(tmp_path / side / "001.png"), np.zeros((300, 400, 3), np.uint8))
    cfg = config.from_data({"source": {"kind": "images", "uri": str(tmp_path)}})
    assert rig.describe(cfg).rig.size == (400, 300)


@pytest.mark.parametrize(
    ("infos", "image", "side", "expected"),
    [
        (["/cam0/camera_info", "/cam1/camera_info"], "/cam0/image_raw", "left",
         "/cam0/camera_info"),
        (["/stereo/left/camera_info", "/stereo/right/camera_info"], "/stereo/left/image_rect",
         "left", "/stereo/left/camera_info"),
        (["/trapflow/left/camera_info", "/trapflow/right/camera_info"],
         "/trapflow/right/image/compressed", "right", "/trapflow/right/camera_info"),
        (["/a/info", "/b/info"], "/c/image", "left", None),  # no way to tell: none
        (["/left_info", "/right_info"], "/c/image", "right", "/right_info"),
    ],
)
def test_camera_info_topic_beside_the_images(
    infos: list[str], image: str, side: str, expected: str | None
) -> None:
    from trapflow.sources.replay import _info_topic

    assert _info_topic(infos, image, side) == expected


def test_rig_from_camera_info() -> None:
    from types import SimpleNamespace

    from trapflow.sources.replay import rig_from_camera_info

    def info(r: StereoRig, right: bool, p: bool = True) -> SimpleNamespace:
        return SimpleNamespace(width=r.width, height=r.height, k=list(r.K.ravel()),
                               p=list(r.projection(right).ravel()) if p else [0.0] * 12)

    got, note = rig_from_camera_info(info(CALIB_TXT, False), info(CALIB_TXT, True), 0.3)
    assert got.id == CALIB_TXT.id and note == ""
    # A monocular P (no -fx*B in the right one): the configured baseline, and a note saying so.
    got, note = rig_from_camera_info(info(CALIB_TXT, False), info(CALIB_TXT, False), 0.3)
    assert got.baseline_m == 0.3 and "rig.baseline_m" in note
    # P unset (all zeros): intrinsics from K.
    got, _ = rig_from_camera_info(info(CALIB_TXT, False, p=False), info(CALIB_TXT, True), 0.3)
    assert (got.fx, got.fy, got.cx, got.cy) == (436.0, 435.0, 370.5, 235.2)
