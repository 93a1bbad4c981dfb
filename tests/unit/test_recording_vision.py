"""Detections in recordings as vision_msgs/Detection2DArray, from the definitions of the
real-data kit (vision_msgs 4.1.1, read in place), read back by two independent readers:
rosbags (with the definitions the file carries) and the mcap library's ROS 2 decoder."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from tests.conformance.conftest import kit_path, realdata_root
from trapflow.recording import vision
from trapflow.recording.recorder import DETECTIONS_PREFIX, TOPIC_LEFT, Recorder
from trapflow.wire.messages import StereoPair

TOPIC = DETECTIONS_PREFIX + "mono_ir"
T0 = 1_751_892_763_000_000_000
# Per pair: the mono_ir lines the normalizer writes (a pair with none gives label "none").
LINES = [
    [{"label": "crab", "confidence": 0.84, "box": [750.0, 98.0, 864.0, 166.0], "track": 3},
     {"label": "scallop", "confidence": 0.51, "box": [10.0, 20.0, 30.5, 60.0], "track": None}],
    [{"label": "none", "confidence": 0.0, "box": []}],
    [{"label": "crab", "confidence": 0.9, "box": [752.0, 99.0, 866.0, 168.0], "track": 3}],
]


@pytest.fixture
def kit_msgs() -> Path:
    """The kit's vision_msgs package folder (msg/ inside); skips without the kit."""
    root = realdata_root()
    if not (root / "MANIFEST.md").is_file():
        pytest.skip(f"real-data kit not found at {root} (set TRAPFLOW_REALDATA to its folder)")
    return kit_path(root, "vision_msgs", "4.1.1")


def _record(out: Path, vision_msgs: str = "") -> Recorder:
    jpg = cv2.imencode(".jpg", np.zeros((48, 64, 3), np.uint8))[1].tobytes()
    with Recorder(out, vision_msgs=vision_msgs) as rec:
        for seq, items in enumerate(LINES):
            t = T0 + seq * 100_000_000
            rec.add_pair(StereoPair(seq=seq, t_wall_ns=t, t_mono_ns=seq, t_left_ns=seq,
                                    t_right_ns=seq, skew_ns=0, encoding="jpeg", width=64,
                                    height=48), jpg, jpg)
            for it in items:
                rec.add_result(json.dumps({"mono_ir": {"seq": seq, **it}}))
        rec.add_result(json.dumps({"tags": {"seq": 2, "corners": []}}))  # not a detection
    return rec


def _expected() -> list[list[tuple[str, float, float, float, float, float, str]]]:
    out = []
    for items in LINES:
        row = []
        for it in items:
            if it["box"]:
                x1, y1, x2, y2 = it["box"]
                track = "" if it["track"] is None else str(it["track"])
                row.append((it["label"], it["confidence"], (x1 + x2) / 2, (y1 + y2) / 2,
                            x2 - x1, y2 - y1, track))
        out.append(row)
    return out


def _flat(msg: Any) -> list[tuple[str, float, float, float, float, float, str]]:
    return [(d.results[0].hypothesis.class_id, d.results[0].hypothesis.score,
             d.bbox.center.position.x, d.bbox.center.position.y, d.bbox.size_x, d.bbox.size_y,
             d.id) for d in msg.detections]


def _read_both(path: Path) -> tuple[list[Any], list[Any], list[int]]:
    """Detection2DArray messages by rosbags and by the mcap reader, and their stamps."""
    # rosbags learns vision_msgs only from the definitions stored in the file itself.
    store = get_typestore(Stores.ROS2_HUMBLE)
    assert "vision_msgs/msg/Detection2DArray" not in store.types
    with AnyReader([path], default_typestore=store) as reader:
        conns = [c for c in reader.connections if c.topic == TOPIC]
        assert [c.msgtype for c in conns] == [vision.DETECTION_ARRAY]
        by_rosbags = [reader.deserialize(raw, c.msgtype)
                      for c, _, raw in reader.messages(connections=conns)]
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        by_mcap = [m.decoded_message for m in reader.iter_decoded_messages(topics=[TOPIC])]
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in by_rosbags]
    return by_rosbags, by_mcap, stamps


def test_detections_from_a_configured_folder_read_back_by_two_readers(
        tmp_path: Path, kit_msgs: Path) -> None:
    """Issue 22 (vision_msgs): detections were not written as Detection2DArray at all."""
    out = tmp_path / "run.mcap"
    rec = _record(out, vision_msgs=str(kit_msgs))  # the package folder: msg/ is found in it
    assert rec.counts.detections == len(LINES)  # one per pair, "seen nothing" included
    by_rosbags, by_mcap, stamps = _read_both(out)
    assert [_flat(m) for m in by_rosbags] == [_flat(m) for m in by_mcap] == _expected()
    assert stamps == [T0 + i * 100_000_000 for i in range(len(LINES))]  # the pairs' times
    assert {m.header.frame_id for m in by_rosbags} == {"trapflow_left"}


def test_detections_from_an_installed_ros_environment(tmp_path: Path, kit_msgs: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """A sourced ROS 2 sets AMENT_PREFIX_PATH; its prefixes hold share/vision_msgs/msg."""
    prefix = tmp_path / "ros"
    (prefix / "share").mkdir(parents=True)
    (prefix / "share" / "vision_msgs").symlink_to(kit_msgs)  # the kit in place, not a copy
    monkeypatch.setenv("AMENT_PREFIX_PATH", f"{tmp_path / 'other'}:{prefix}")
    out = tmp_path / "run.mcap"
    _record(out)
    by_rosbags, by_mcap, _ = _read_both(out)
    assert [_flat(m) for m in by_rosbags] == [_flat(m) for m in by_mcap] == _expected()


def test_without_definitions_the_recording_says_so_once_and_keeps_the_rest(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.delenv("AMENT_PREFIX_PATH", raising=False)
    out = tmp_path / "run.mcap"
    with caplog.at_level(logging.WARNING):
        rec = _record(out)
    said = [r.getMessage() for r in caplog.records if "vision_msgs" in r.getMessage()]
    assert len(said) == 1 and "no vision_msgs definitions found" in said[0], said
    assert "AMENT_PREFIX_PATH" in said[0] and "recording.vision_msgs" in said[0]
    assert rec.counts.detections == 0
    with AnyReader([out]) as reader:
        topics = {c.topic for c in reader.connections}
    assert TOPIC not in topics
    assert {TOPIC_LEFT, "/trapflow/results/mono_ir", "/trapflow/pairs"} <= topics


def test_definitions_of_another_layout_are_refused_with_the_reason(
        tmp_path: Path, kit_msgs: Path) -> None:
    """vision_msgs 3 had Pose2D x, y, theta: the message built here would not encode."""
    folder = tmp_path / "msg"
    folder.mkdir()
    for src in (kit_msgs / "msg").glob("*.msg"):
        (folder / src.name).symlink_to(src)
    (folder / "Pose2D.msg").unlink()
    (folder / "Pose2D.msg").write_text("float64 x\nfloat64 y\nfloat64 theta\n")
    with pytest.raises(ValueError, match=r"expected vision_msgs 4 \(Pose2D with a position\)"):
        vision.find(str(folder), env={})
