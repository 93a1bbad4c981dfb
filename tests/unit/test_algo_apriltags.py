"""AprilTag poses against tags rendered with a known pose, in the C library's tag frame."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from trapflow_workers import apriltags
from trapflow_workers.apriltags import AprilTags, tag_object_points

from tests.kits.scenes import pose, rot_x, rot_z, tag_image
from trapflow.calibration.camera import StereoRig
from trapflow.errors import ConfigError, WorkerError
from trapflow.testing.kit import make_context, make_pair

RIG = StereoRig.from_fov(1280, 720, 70.0, 0.12)
# The C library comes with the optional tags extra, which has no wheel on every platform
# (none for aarch64 Linux): its cases skip where it is missing, the OpenCV ones still run.
C_LIBRARY = apriltags._c_library_available()
DETECTORS = [pytest.param("apriltag", marks=pytest.mark.skipif(
    not C_LIBRARY, reason="pupil-apriltags (the tags extra) is not installed")), "opencv"]


def _detector(**params: Any) -> AprilTags:
    tags = AprilTags()
    tags.configure(params, make_context(RIG, pool="tags"))
    return tags


# tag_image draws OpenCV's marker (its code turned 180 deg from the official tag image) in a
# frame x right, y up, z out of it; the C library's frame of that printed tag (x right, y down
# of the upright official image, z into the tag) is that frame turned 180 deg about y.
OPENCV_DRAWN_TO_C = np.diag([-1.0, 1.0, -1.0, 1.0])


def _facing(yaw_deg: float, tilt_deg: float, t: tuple[float, float, float]) -> np.ndarray:
    """Tag (C library frame) to camera: upright and facing the camera at yaw = tilt = 0."""
    r = rot_z(math.radians(yaw_deg)) @ rot_x(math.radians(tilt_deg))
    return pose(r, np.array(t))


def _render(tag_id: int, size: float, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The tag seen at pose truth (C library frame) and its corners p0..p3 in pixels."""
    img, _ = tag_image(RIG, tag_id, size, truth @ OPENCV_DRAWN_TO_C)
    cam = (truth[:3, :3] @ tag_object_points(size).T).T + truth[:3, 3]
    uv = (RIG.K @ cam.T).T
    return img, uv[:, :2] / uv[:, 2:]


@pytest.mark.parametrize("detector", DETECTORS)
@pytest.mark.parametrize(
    ("tag_id", "yaw", "tilt", "t"),
    [
        (0, 0, 0, (0.0, 0.0, 1.0)),
        (7, 25, 30, (0.15, -0.05, 1.2)),
        (123, -40, -20, (-0.2, 0.1, 0.8)),
        (586, 90, 10, (0.0, 0.2, 1.5)),
    ],
)
def test_pose_matches_rendered_tag(
    tag_id: int, yaw: float, tilt: float, t: tuple[float, float, float], detector: str
) -> None:
    """Both detectors report the C library's corner order and frame (regression, issue 12:
    OpenCV's order and a pose turned 180 deg about the viewing axis were reported)."""
    truth = _facing(yaw, tilt, t)
    img, corners = _render(tag_id, 0.1, truth)
    res = _detector(tag_size_m=0.1, detector=detector).process(make_pair(img))
    assert [tag.id for tag in res.tags] == [tag_id]
    tag = res.tags[0]
    np.testing.assert_allclose(tag.corners, corners, atol=1.0)
    np.testing.assert_allclose(tag.translation, t, atol=0.01 * np.linalg.norm(t))
    r = np.reshape(tag.rotation, (3, 3))
    angle = math.degrees(math.acos(np.clip((np.trace(r.T @ truth[:3, :3]) - 1) / 2, -1, 1)))
    assert angle < 2.0
    assert tag.error < 1.0


@pytest.mark.parametrize("detector", DETECTORS)
@pytest.mark.parametrize(
    ("family", "code"),
    [("25h9", cv2.aruco.DICT_APRILTAG_25h9), ("16h5", cv2.aruco.DICT_APRILTAG_16h5)],
)
def test_other_families_keep_the_order_and_frame(family: str, code: int, detector: str) -> None:
    """OpenCV holds every APRILTAG family turned 180 deg; both detectors agree on all of them."""
    truth = _facing(30, 25, (0.05, -0.03, 0.9))
    img, _ = tag_image(RIG, 11, 0.1, truth @ OPENCV_DRAWN_TO_C, family=code)
    cam = (truth[:3, :3] @ tag_object_points(0.1).T).T + truth[:3, 3]
    uv = (RIG.K @ cam.T).T
    tags = _detector(family=family, detector=detector, tag_size_m=0.1).process(make_pair(img)).tags
    assert [t.id for t in tags] == [11]
    np.testing.assert_allclose(tags[0].corners, uv[:, :2] / uv[:, 2:], atol=1.0)
    r = np.reshape(tags[0].rotation, (3, 3))
    assert math.degrees(math.acos(np.clip((np.trace(r.T @ truth[:3, :3]) - 1) / 2, -1, 1))) < 2


def test_per_id_size_scales_the_distance() -> None:
    truth = _facing(0, 0, (0.0, 0.0, 1.0))
    img, _ = _render(5, 0.1, truth)
    tag = _detector(tag_size_m=0.1, sizes={5: 0.2}).process(make_pair(img)).tags[0]
    assert tag.translation[2] == pytest.approx(2.0, rel=0.01)


def test_empty_scene_and_other_family() -> None:
    assert _detector().process(make_pair(np.full((720, 1280, 3), 90, np.uint8))).tags == []
    img, _ = _render(3, 0.1, _facing(0, 0, (0, 0, 1.0)))
    assert _detector(family="25h9").process(make_pair(img)).tags == []


@pytest.mark.parametrize(
    ("params", "error"),
    [
        ({"family": "41h12"}, r"pools\.tags\.params\.family"),
        ({"tag_size_m": -1}, r"pools\.tags\.params\.tag_size_m"),
        ({"refine": "apriltag"}, r"pools\.tags\.params\.refine"),
        ({"detector": "aruco"}, r"pools\.tags\.params\.detector"),
        ({"decimate": 0.5}, r"pools\.tags\.params\.decimate"),
        ({"detector": "apriltag", "family": "36h10"}, r"detector: expected a family .*'36h10'"),
        ({"calibration": "{tmp}/missing.yaml"}, "cannot read calibration"),
        ({"calibration": "{tmp}/c.yaml"}, "missing field 'cx'"),
    ],
)
def test_configure_rejects(tmp_path: Path, params: dict[str, Any], error: str) -> None:
    (tmp_path / "c.yaml").write_text("fx: 900\nfy: 900\ncy: 360\nbaseline_m: 0.12\n")
    params = {k: v.format(tmp=tmp_path) if isinstance(v, str) else v for k, v in params.items()}
    with pytest.raises(WorkerError, match=error):
        _detector(**params)


@pytest.mark.parametrize(
    ("params", "source_m", "size_m"),
    [
        ({}, 0.12, 0.12),  # the source says: taken as it is
        ({"tag_size_m": 0.12}, 0.12, 0.12),  # the config agrees with the source
        ({"tag_size_m": 0.16}, None, 0.16),  # a camera knows no size: the config's
        ({}, None, apriltags.FALLBACK_TAG_SIZE_M),  # nobody says: the fallback (logged)
    ],
)
def test_tag_size_comes_from_one_place(params: dict[str, Any], source_m: float | None,
                                       size_m: float) -> None:
    tags = AprilTags()
    tags.configure(params, make_context(RIG, pool="tags", tag_size_m=source_m))
    assert tags.size == size_m


@pytest.mark.parametrize(
    ("params", "key"),
    [
        ({"tag_size_m": 0.1}, "tag_size_m"),
        ({"sizes": {3: 0.2}}, "sizes.3"),
    ],
)
def test_tag_size_against_the_source_is_an_error(params: dict[str, Any], key: str) -> None:
    """Regression (issue 24): the tags pool assumed 0.10 m where the synthetic world lays
    0.12 m tags, so every tag range came out 16.5 % short without a word."""
    tags = AprilTags()
    with pytest.raises(ConfigError) as got:
        tags.configure(params, make_context(RIG, pool="tags", tag_size_m=0.12))
    text = str(got.value)
    assert text.startswith(f"pools.tags.params.{key}: expected the source's tag size 0.12 m")
    assert "got 0.1 m" in text or "got 0.2 m" in text
    assert "remove the key" in text and "source.options.tag_size_m" in text


def test_wrong_frame_size_is_a_worker_error() -> None:
    small = np.zeros((480, 640, 3), np.uint8)
    with pytest.raises(WorkerError, match="expected 1280x720"):
        _detector().process(make_pair(small))


def test_without_the_c_library(monkeypatch: pytest.MonkeyPatch) -> None:
    """auto falls back to OpenCV (same order, same frame); asking for the C library fails at
    configure with the fix."""
    assert _detector().backend == ("apriltag" if C_LIBRARY else "opencv")
    assert _detector(family="36h10").backend == "opencv"
    monkeypatch.setattr(apriltags, "_c_library_available", lambda: False)
    assert _detector().backend == "opencv"
    with pytest.raises(WorkerError, match=r"pip install trapflow\[tags\]"):
        _detector(detector="apriltag")
