"""AprilTag poses against tags rendered with a known pose."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from trapflow_workers.apriltags import AprilTags
from trapflow_workers.testkit import make_context, make_pair
from trapflow_workers.testkit_scenes import pose, rot_x, rot_z, tag_image

from trapflow.camera import StereoRig
from trapflow.errors import WorkerError

RIG = StereoRig.from_fov(1280, 720, 70.0, 0.12)


def _detector(**params: Any) -> AprilTags:
    tags = AprilTags()
    tags.configure(params, make_context(RIG, pool="tags"))
    return tags


def _facing(yaw_deg: float, tilt_deg: float, t: tuple[float, float, float]) -> np.ndarray:
    # A tag facing the camera has its z axis pointing back at it: rotate pi about x.
    r = rot_x(math.pi) @ rot_z(math.radians(yaw_deg)) @ rot_x(math.radians(tilt_deg))
    return pose(r, np.array(t))


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
    tag_id: int, yaw: float, tilt: float, t: tuple[float, float, float]
) -> None:
    truth = _facing(yaw, tilt, t)
    img, corners = tag_image(RIG, tag_id, 0.1, truth)
    res = _detector(tag_size_m=0.1).process(make_pair(img))
    assert [tag.id for tag in res.tags] == [tag_id]
    tag = res.tags[0]
    np.testing.assert_allclose(tag.corners, corners, atol=1.0)
    np.testing.assert_allclose(tag.translation, t, atol=0.01 * np.linalg.norm(t))
    r = np.reshape(tag.rotation, (3, 3))
    angle = math.degrees(math.acos(np.clip((np.trace(r.T @ truth[:3, :3]) - 1) / 2, -1, 1)))
    assert angle < 2.0
    assert tag.error < 1.0


def test_per_id_size_scales_the_distance() -> None:
    truth = _facing(0, 0, (0.0, 0.0, 1.0))
    img, _ = tag_image(RIG, 5, 0.1, truth)
    tag = _detector(tag_size_m=0.1, sizes={5: 0.2}).process(make_pair(img)).tags[0]
    assert tag.translation[2] == pytest.approx(2.0, rel=0.01)


def test_empty_scene_and_other_family() -> None:
    assert _detector().process(make_pair(np.full((720, 1280, 3), 90, np.uint8))).tags == []
    img, _ = tag_image(RIG, 3, 0.1, _facing(0, 0, (0, 0, 1.0)))
    assert _detector(family="25h9").process(make_pair(img)).tags == []


@pytest.mark.parametrize(
    ("params", "error"),
    [
        ({"family": "41h12"}, r"pools\.tags\.params\.family"),
        ({"tag_size_m": -1}, r"pools\.tags\.params\.tag_size_m"),
        ({"calibration": "{tmp}/missing.yaml"}, "cannot read calibration"),
        ({"calibration": "{tmp}/c.yaml"}, "missing field 'cx'"),
    ],
)
def test_configure_rejects(tmp_path: Path, params: dict[str, Any], error: str) -> None:
    (tmp_path / "c.yaml").write_text("fx: 900\nfy: 900\ncy: 360\nbaseline_m: 0.12\n")
    params = {k: v.format(tmp=tmp_path) if isinstance(v, str) else v for k, v in params.items()}
    with pytest.raises(WorkerError, match=error):
        _detector(**params)


def test_wrong_frame_size_is_a_worker_error() -> None:
    small = np.zeros((480, 640, 3), np.uint8)
    with pytest.raises(WorkerError, match="expected 1280x720"):
        _detector().process(make_pair(small))
