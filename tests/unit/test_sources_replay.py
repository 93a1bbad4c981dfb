"""Replay of trapflow recordings and of ROS 2 bags written with rosbags (sqlite3 and MCAP)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer

from tests.builders import (
    PERIOD,
    T0,
    TS,
    H,
    W,
    drain,
    drain_skipping,
    img,
    level,
    ros_header,
    write_bag,
    write_stereo_msg_bag,
    write_trapflow,
)
from trapflow.calibration.camera import StereoRig
from trapflow.config.schema import SourceConfig, from_data
from trapflow.recording.recorder import Recorder
from trapflow.sources import rig
from trapflow.sources.base import SkipPair, Source, SourceError
from trapflow.sources.factory import open_source
from trapflow.sources.replay import ReplaySource
from trapflow.wire.messages import StereoPair

RIG = StereoRig.from_fov(W, H, 70.0, 0.12)


def make(path: Path, **options: Any) -> Source:
    loop = options.pop("loop", False)
    return open_source(SourceConfig(kind="replay", uri=str(path), loop=loop,
                                    options={"rate": 0, **options}), RIG)


def test_replays_a_trapflow_recording(tmp_path: Path) -> None:
    write_trapflow(tmp_path / "run.mcap", 6)
    src = make(tmp_path / "run.mcap")
    got = drain(src)
    assert [level(f.left, 0) for f in got] == list(range(6))
    assert [level(f.right, 1) for f in got] == list(range(6))
    assert all(f.t_right_ns - f.t_left_ns == 3_000_000 for f in got)
    assert isinstance(src, ReplaySource) and src.pairs_read == 6
    assert src.skew.skew_max_ns == 3_000_000
    assert ReplaySource(src.cfg, RIG).count_pairs() == 6


@pytest.mark.parametrize("plugin", [StoragePlugin.SQLITE3, StoragePlugin.MCAP])
def test_replays_a_ros2_bag_pairing_by_stamp(tmp_path: Path, plugin: StoragePlugin) -> None:
    write_bag(tmp_path / "bag", 8, plugin, drop_right=3)
    src = make(tmp_path / "bag")
    got = drain(src)
    assert [level(f.left, 0) for f in got] == [0, 1, 2, 4, 5, 6, 7]
    assert [level(f.right, 1) for f in got] == [0, 1, 2, 4, 5, 6, 7]
    assert isinstance(src, ReplaySource)
    assert src.skew.dropped_left == 1 and src.skew.pairs == 7


def test_replay_keeps_original_timing(tmp_path: Path) -> None:
    write_bag(tmp_path / "bag", 5, StoragePlugin.SQLITE3)
    got = drain(make(tmp_path / "bag", rate=4.0))
    span = got[-1].t_left_ns - got[0].t_left_ns
    assert span >= 4 * PERIOD / 4.0 * 0.95  # never faster than the scaled original timing


def test_replay_loops(tmp_path: Path) -> None:
    write_trapflow(tmp_path / "run.mcap", 3)
    got = drain(make(tmp_path / "run.mcap", loop=True), limit=7)
    assert [level(f.left, 0) for f in got] == [0, 1, 2, 0, 1, 2, 0]


def test_custom_stereo_message_with_user_definition(tmp_path: Path) -> None:
    msg_def = write_stereo_msg_bag(tmp_path, 4, right_after_ns=1000)
    got = drain(make(tmp_path / "bag", msg_type="trap_msgs/msg/StereoImage",
                     msg_def=str(msg_def)))
    assert [level(f.right, 1) for f in got] == [0, 1, 2, 3]
    assert all(f.t_right_ns - f.t_left_ns == 1000 for f in got)


def no_images(d: Path) -> Path:
    with Writer(d / "bag", version=8) as w:
        c = w.add_connection("/chatter", "std_msgs/msg/String", typestore=TS)
        w.write(c, T0, TS.serialize_cdr(TS.types["std_msgs/msg/String"](data="hi"),
                                        "std_msgs/msg/String"))
    return d / "bag"


@pytest.mark.parametrize(
    ("setup", "options", "error"),
    [
        (lambda d: d / "missing.mcap", {}, "recording not found"),
        (lambda d: (d / "junk.mcap").write_bytes(b"\0" * 100) and d / "junk.mcap", {},
         "cannot read .* as a ROS 2 bag"),
        (no_images, {}, "no image topics .* /chatter \\(std_msgs/msg/String\\)"),
        (lambda d: (write_bag(d / "b", 2, StoragePlugin.SQLITE3), d / "b")[1],
         {"left_topic": "/left", "right_topic": "/cam1/image_raw"}, "image topic '/left' not in"),
        (lambda d: (write_bag(d / "b", 2, StoragePlugin.SQLITE3), d / "b")[1],
         {"msg_type": "x/msg/Stereo"}, "no topic of type x/msg/Stereo"),
    ],
)
def test_bad_recordings_fail_with_one_clear_reason(
    tmp_path: Path, setup: Any, options: dict[str, Any], error: str
) -> None:
    src = make(setup(tmp_path), **options)
    with pytest.raises(SourceError, match=error):
        src.open()
        src.read()
    src.close()


def compressed(t: int, data: bytes) -> Any:
    Compressed = TS.types["sensor_msgs/msg/CompressedImage"]  # noqa: N806 - a message class
    return Compressed(header=ros_header(t, "cam"), format="jpeg",
                      data=np.frombuffer(data, np.uint8))


def write_faulty_bag(path: Path, n: int) -> dict[int, str]:
    """CompressedImage pairs where pair 1's left message does not deserialize, pair 3's left
    is not a JPEG, pair 4's right is cut short and pair 6's right has another size."""
    faults = {1: "undecodable", 3: "unreadable", 4: "truncated", 6: "size"}
    ctype = "sensor_msgs/msg/CompressedImage"
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        cl = w.add_connection("/left/image/compressed", ctype, typestore=TS)
        cr = w.add_connection("/right/image/compressed", ctype, typestore=TS)
        for i in range(n):
            t = T0 + i * PERIOD
            jl = cv2.imencode(".jpg", img(i, 0))[1].tobytes()
            jr = cv2.imencode(".jpg", img(i, 1))[1].tobytes()
            if faults.get(i) == "unreadable":
                jl = b"\xff\xd8 but no image at all \xff\xd9"
            if faults.get(i) == "truncated":
                jr = jr[: len(jr) // 2]
            if faults.get(i) == "size":
                jr = cv2.imencode(".jpg", np.zeros((H // 2, W // 2, 3), np.uint8))[1].tobytes()
            left = TS.serialize_cdr(compressed(t, jl), ctype)
            if faults.get(i) == "undecodable":
                left = left[:24]  # a CDR message cut inside its data field
            w.write(cl, t, left)
            w.write(cr, t, TS.serialize_cdr(compressed(t, jr), ctype))
    return faults


def test_bag_messages_that_do_not_decode_are_skipped_and_the_bag_goes_on(tmp_path: Path) -> None:
    """Regression (issue 12, item 2): a bag message that did not decode was retried forever."""
    faults = write_faulty_bag(tmp_path / "bag", 8)
    src = make(tmp_path / "bag")
    got, skipped = drain_skipping(src, 20)
    assert [level(f.left, 0) for f in got] == [i for i in range(8) if i not in faults]
    assert [e.kind for e in skipped] == list(faults.values())
    # Each names the message: index i*2 is pair i's left, i*2+1 its right (time order).
    assert "message 2 on /left/image/compressed" in str(skipped[0])
    assert "bag message 6:" in str(skipped[1])
    assert "message 9: CompressedImage ('jpeg'): JPEG of" in str(skipped[2])
    assert "messages 12 and 13: left is 64x48, right is 32x24" in str(skipped[3])
    assert isinstance(src, ReplaySource) and src.pairs_read == 8


def test_a_recording_damaged_mid_file_ends_the_source_with_where(tmp_path: Path) -> None:
    """A chunk that fails its checksum: the pairs before it are read, then one SourceError
    (not a SkipPair: nothing after it can be trusted in order) names the place."""
    rec = tmp_path / "run.mcap"
    with Recorder(rec) as r:
        for i in range(40):
            h = StereoPair(seq=i, t_wall_ns=T0 + i * PERIOD, t_mono_ns=i, t_left_ns=i,
                           t_right_ns=i, skew_ns=0, encoding="jpeg", width=W, height=H)
            noise = np.random.default_rng(i).integers(0, 255, (H, W, 3), np.uint8)
            jpg = cv2.imencode(".jpg", noise)[1].tobytes()
            r.add_pair(h, jpg, jpg)
            if i % 10 == 9:
                r._writer._writer.flush()  # four chunks of ten pairs
    data = bytearray(rec.read_bytes())
    mid = len(data) // 2
    data[mid : mid + 64] = bytes(64)
    rec.write_bytes(bytes(data))
    src = make(rec)
    src.open()
    got = 0
    with pytest.raises(SourceError, match="run.mcap is damaged after message") as info:
        for _ in range(50):
            if src.read() is None:
                break
            got += 1
    src.close()
    assert not isinstance(info.value, SkipPair)
    assert 10 <= got < 40


def test_a_custom_stereo_message_tells_its_frame_size(tmp_path: Path) -> None:
    """A bag of one user-defined stereo message: the rig takes the size of its first images."""
    msg_def = write_stereo_msg_bag(tmp_path, 2)
    found = rig.describe(from_data({"source": {"kind": "replay", "uri": str(tmp_path / "bag"),
                                           "options": {
                                               "msg_type": "trap_msgs/msg/StereoImage",
                                               "msg_def": str(msg_def)}}}))
    assert found.rig == StereoRig.from_fov(W, H, 70.0, 0.12)
    assert "trap_msgs/msg/StereoImage" in found.origin
