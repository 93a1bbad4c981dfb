"""The rig's poses from VO by capture time, and tracks' speeds over the ground with them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from trapflow.batch.run import rig_poses
from trapflow.config.schema import ObserveConfig
from trapflow.tracking.rigpose import RigPoses, ground_positions
from trapflow.tracking.stage import View, aggregate, track_pairs


def _pose(x: float, yaw: float = 0.0) -> tuple[float, ...]:
    """A 3x4 camera-to-world pose: turned by yaw about the camera's y axis, moved x along
    the world's x."""
    c, s = math.cos(yaw), math.sin(yaw)
    return (c, 0.0, s, x, 0.0, 1.0, 0.0, 0.0, -s, 0.0, c, 0.0)


def _chain(*entries: tuple[float, float, bool, bool]) -> RigPoses:
    poses = RigPoses()
    for t, x, ok, reinit in entries:
        poses.add(t, _pose(x), ok, reinit)
    return poses


@pytest.mark.parametrize(("entries", "t", "expected"), [
    # no pose at all
    ((), 1.0, None),
    # the pair's own pose
    (((1.0, 0.5, True, False),), 1.0, (0, 0.5)),
    # farther than the tolerance (0.15 s) from any pose: none rather than a stale one
    (((1.0, 0.5, True, False),), 1.3, None),
    # between two poses of one chain: the translation interpolated
    (((1.0, 0.0, True, False), (1.2, 0.2, True, False)), 1.05, (0, 0.05)),
    # poses that came out of capture order are kept in capture order
    (((1.2, 0.2, True, False), (1.0, 0.0, True, False)), 1.15, (0, 0.15)),
    # a result that is not ok carries the last good pose, not its own: skipped
    (((1.0, 0.0, True, False), (1.1, 9.0, False, False)), 1.1, (0, 0.0)),
    # a re-initialisation starts a new chain: never interpolated across it
    (((1.0, 0.0, True, False), (1.1, 0.7, False, True)), 1.06, (1, 0.7)),
])
def test_pose_at(entries: tuple[tuple[float, float, bool, bool], ...], t: float,
                 expected: tuple[int, float] | None) -> None:
    got = _chain(*entries).at(t)
    if expected is None:
        assert got is None
    else:
        assert got is not None
        assert got[0] == expected[0]
        assert got[1][0, 3] == pytest.approx(expected[1])


def test_old_poses_are_forgotten() -> None:
    poses = RigPoses(keep_s=10.0)
    for i in range(30):
        poses.add(float(i), _pose(0.0), True, False)
    assert poses.at(5.0) is None and poses.at(29.0) is not None
    assert len(poses.times) == 11


def test_positions_of_the_chain_holding_most_views() -> None:
    """Positions of two VO chains are not in one frame: the larger chain's views only."""
    poses = _chain((0.0, 0.0, True, True), (1.0, 1.0, True, False), (2.0, 5.0, False, True),
                   (3.0, 6.0, True, False), (4.0, 7.0, True, False))
    got = ground_positions([0.0, 1.0, 2.0, 3.0, 4.0], [(0.0, 0.0, 1.0)] * 5, poses)
    assert got is not None
    assert list(got[0]) == [2.0, 3.0, 4.0]
    assert list(got[1][:, 0]) == pytest.approx([5.0, 6.0, 7.0])


def _walk(rig_speed: float, yaw_rate: float) -> tuple[list[View], RigPoses]:
    """An animal walking 0.1 m/s along the world's z, seen from a rig that moves along x and
    turns: its views in the camera frame and VO's poses."""
    views, poses = [], RigPoses()
    for i in range(20):
        t = 0.2 * i
        pose = np.eye(4)
        pose[:3, :] = np.array(_pose(rig_speed * t, yaw_rate * t)).reshape(3, 4)
        animal = np.array([0.3, 0.5, 1.5 + 0.1 * t])
        cam = np.linalg.inv(pose) @ np.append(animal, 1.0)
        views.append(View(100.0 + t, (cam[0], cam[1], cam[2]), 0.2, 0.01))
        poses.add(100.0 + t, tuple(pose[:3].ravel()), True, i == 0)
    return views, poses


@pytest.mark.parametrize(("rig_speed", "yaw_rate"), [
    (0.0, 0.0),  # a still rig: the same speed in either frame
    (0.15, 0.0),  # the rig drifts as fast as the animal walks
    (0.15, 0.1),  # and turns
])
def test_speed_over_the_ground(rig_speed: float, yaw_rate: float) -> None:
    views, poses = _walk(rig_speed, yaw_rate)
    got = aggregate(views, poses)
    assert got["speed_m_s"] == pytest.approx(0.1, abs=1e-3)
    assert got["speed_frame"] == "ground"
    raw = aggregate(views)  # no VO: the rig taken to stand still
    assert raw["speed_frame"] == "camera"
    if rig_speed:
        assert abs(raw["speed_m_s"] - 0.1) > 0.05


def test_no_speed_without_the_views_poses() -> None:
    """With VO running, a track none of whose views has a pose gets no speed rather than
    one measured against the moving rig."""
    views, _ = _walk(0.15, 0.0)
    poses = _chain((500.0, 0.0, True, True))
    got = aggregate(views, poses)
    assert "speed_m_s" not in got and "speed_frame" not in got
    assert got["length_m"] == pytest.approx(0.2)


def test_reanalysis_takes_vo_lines_poses() -> None:
    """`trapflow process` tracks an input's lines as the live normalizer does: its VO lines'
    poses (results.jsonl shape) take the rig's motion out of the tracks' speeds."""
    lines: list[dict[str, object]] = []
    pairs = []
    for i in range(12):
        t = 0.2 * i
        stamp = f"2026-11-25 14:00:{t:06.3f}"
        pose = np.array(_pose(0.15 * t)).reshape(3, 4)  # the rig drifts 0.15 m/s along x
        animal = np.array([0.1 * t, 0.2, 1.5])  # the animal walks 0.1 m/s along x too
        cam = animal - pose[:, 3]
        lines.append({"stereo_vo": {"timestamp": stamp, "seq": i, "ok": True,
                                    "pose": pose.tolist(), **({"reinit": True} if i == 0
                                                              else {})}})
        item = {"timestamp": stamp, "seq": i, "label": "crab", "confidence": 0.9,
                "box": [300.0 - 5 * i, 100.0, 340.0 - 5 * i, 130.0], "xyz": cam.tolist(),
                "length_m": 0.1, "length_sd_m": 0.01}
        lines.append({"mono_ir": item})
        pairs.append((1795615200 * 10**9 + int(round(t * 1e9)), [item]))
    poses = rig_poses(lines)
    assert poses.at(1795615200.4) is not None
    got = track_pairs(pairs, ObserveConfig(interval_s=3600), poses).tracks
    assert len(got) == 1
    assert got[0]["track"]["speed_frame"] == "ground"
    assert got[0]["track"]["speed_m_s"] == pytest.approx(0.1, abs=0.005)
