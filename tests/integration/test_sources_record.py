"""Recording: a real PUB tap feeds record(); the MCAP is read back with rosbags."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
import zmq
from rosbags.highlevel import AnyReader

from trapflow.recording.recorder import (
    TOPIC_LEFT,
    TOPIC_PAIRS,
    TOPIC_RIGHT,
    RecordCounts,
    Recorder,
    RecorderError,
    record,
)
from trapflow.wire.messages import StereoPair, encode
from trapflow.wire.tap_msgs import TOPIC_IMAGE, TOPIC_RESULT

W, H = 96, 64
T_WALL0 = 1_751_892_763_000_000_000


def jpeg(i: int, side: int) -> bytes:
    img = np.zeros((H, W, 3), np.uint8)
    cv2.putText(img, str(i), (10, 50), cv2.FONT_HERSHEY_SIMPLEX, 1.5, (255, 255, 255 * side), 3)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 80])
    assert ok
    return buf.tobytes()


def header(i: int) -> StereoPair:
    t_mono = 5_000_000_000 + i * 66_000_000
    return StereoPair(seq=i, t_wall_ns=T_WALL0 + i * 66_000_000, t_mono_ns=t_mono,
                      t_left_ns=t_mono - 2_000_000, t_right_ns=t_mono - 1_000_000,
                      skew_ns=1_000_000, encoding="jpeg", width=W, height=H, source="test")


def result(algo: str, seq: int) -> bytes:
    body = {"timestamp": "2025-07-07 12:52:43", "seq": seq, "label": "crab", "confidence": 0.71}
    return json.dumps({algo: body}).encode()


@pytest.fixture
def tap(tmp_path: Path) -> Iterator[tuple[str, zmq.Socket[bytes]]]:
    ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context.instance()
    pub = ctx.socket(zmq.XPUB)  # XPUB: a PUB that also tells us when the recorder subscribed
    pub.setsockopt(zmq.LINGER, 0)
    endpoint = f"ipc://{tmp_path}/tap.sock"
    pub.bind(endpoint)
    yield endpoint, pub
    pub.close(linger=0)


def wait_subscribed(pub: zmq.Socket[bytes], topics: set[bytes], timeout: float = 5.0) -> None:
    seen: set[bytes] = set()
    deadline = time.monotonic() + timeout
    while seen != topics:
        assert pub.poll(int(max(deadline - time.monotonic(), 0) * 1000)), f"only {seen}"
        msg = pub.recv()
        if msg[:1] == b"\x01":
            seen.add(msg[1:])


def poll_for(pred: object, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():  # type: ignore[operator]
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def read_back(path: Path) -> dict[str, list[tuple[int, object]]]:
    out: dict[str, list[tuple[int, object]]] = {}
    with AnyReader([path]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        for conn, t, raw in reader.messages():
            out.setdefault(conn.topic, []).append((t, reader.deserialize(raw, conn.msgtype)))
    out["__types__"] = [(0, types)]
    return out


@pytest.mark.timeout(30)
def test_record_from_tap_reads_back_as_rosbag2(
    tmp_path: Path, tap: tuple[str, zmq.Socket[bytes]]
) -> None:
    endpoint, pub = tap
    out = tmp_path / "run.mcap"
    stop = threading.Event()
    counts = RecordCounts()
    thread = threading.Thread(target=record, args=(endpoint, out, stop, counts))
    thread.start()
    try:
        wait_subscribed(pub, {TOPIC_IMAGE, TOPIC_RESULT})
        n = 12
        for i in range(n):
            pub.send_multipart([TOPIC_IMAGE, encode(header(i)), jpeg(i, 0), jpeg(i, 1)])
            pub.send_multipart([TOPIC_RESULT, result("mono_ir", i)])
            if i % 3 == 0:
                pub.send_multipart([TOPIC_RESULT, result("stereo_ir", i)])
        pub.send_multipart([TOPIC_IMAGE, b"garbage", b"x", b"y"])
        poll_for(lambda: counts.pairs == n and counts.total_results == n + 4 and counts.malformed)
    finally:
        stop.set()
        thread.join(10)
    assert not thread.is_alive()
    assert out.is_file() and not (tmp_path / "run.mcap.part").exists()

    got = read_back(out)
    types = got.pop("__types__")[0][1]
    assert types == {
        TOPIC_LEFT: "sensor_msgs/msg/CompressedImage",
        TOPIC_RIGHT: "sensor_msgs/msg/CompressedImage",
        TOPIC_PAIRS: "std_msgs/msg/String",
        "/trapflow/results/mono_ir": "std_msgs/msg/String",
        "/trapflow/results/stereo_ir": "std_msgs/msg/String",
        "/trapflow/left/annotations/mono_ir": "foxglove_msgs/msg/ImageAnnotations",
    }
    assert {k: len(v) for k, v in got.items()} == {
        TOPIC_LEFT: n, TOPIC_RIGHT: n, TOPIC_PAIRS: n,
        "/trapflow/results/mono_ir": n, "/trapflow/results/stereo_ir": 4,
        "/trapflow/left/annotations/mono_ir": n,  # one per pair; these have no box to draw
    }
    sides = zip(got[TOPIC_LEFT], got[TOPIC_RIGHT], strict=True)
    for i, ((tl, left), (tr, right)) in enumerate(sides):
        h = header(i)
        assert tl == h.t_wall_ns - 2_000_000 and tr == h.t_wall_ns - 1_000_000
        stamp = left.header.stamp  # type: ignore[attr-defined]
        assert stamp.sec * 1_000_000_000 + stamp.nanosec == tl
        assert left.format == "jpeg"  # type: ignore[attr-defined]
        assert bytes(left.data) == jpeg(i, 0) and bytes(right.data) == jpeg(i, 1)  # type: ignore[attr-defined]
        img = cv2.imdecode(np.frombuffer(bytes(left.data), np.uint8), cv2.IMREAD_COLOR)  # type: ignore[attr-defined]
        assert img.shape == (H, W, 3)
    for t, msg in got["/trapflow/results/mono_ir"]:
        seq = json.loads(msg.data)["mono_ir"]["seq"]  # type: ignore[attr-defined]
        assert t == header(seq).t_wall_ns - 2_000_000  # stamped with its pair's capture time
    meta = [json.loads(m.data) for _, m in got[TOPIC_PAIRS]]  # type: ignore[attr-defined]
    assert [m["seq"] for m in meta] == list(range(n))


def test_raw_pairs_are_recorded_as_jpeg(tmp_path: Path) -> None:
    img = np.full((H, W, 3), 128, np.uint8)
    h = StereoPair(seq=0, t_wall_ns=T_WALL0, t_mono_ns=1, t_left_ns=1, t_right_ns=1, skew_ns=0,
                   encoding="raw", width=W, height=H)
    with Recorder(tmp_path / "raw.mcap") as rec:
        rec.add_pair(h, img.tobytes(), img.tobytes())
    got = read_back(tmp_path / "raw.mcap")
    data = bytes(got[TOPIC_LEFT][0][1].data)  # type: ignore[attr-defined]
    dec = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert abs(float(dec.mean()) - 128) < 2


@pytest.mark.parametrize(
    ("line", "error"),
    [
        (b"not json", "expected one JSON object"),
        (b"[1, 2]", "expected one {algorithm"),
        (b'{"a": {}, "b": {}}', "expected one {algorithm"),
        (b'{"bad name": {"seq": 1}}', "expected an algorithm name"),
    ],
)
def test_bad_result_lines_are_rejected(tmp_path: Path, line: bytes, error: str) -> None:
    with Recorder(tmp_path / "r.mcap") as rec, pytest.raises(RecorderError, match=error):
        rec.add_result(line)


def test_unwritable_output_is_one_clear_error(tmp_path: Path) -> None:
    with pytest.raises(RecorderError, match="cannot write recording"):
        Recorder(tmp_path / "no" / "such" / "dir" / "x.mcap")


def test_results_ahead_of_their_pair_take_its_capture_time_and_order(tmp_path: Path) -> None:
    """Regression: under load a result reached the recorder before its pair (images come
    through their own tap connection) and was stamped with its receive time, so readers
    sorted it after later results and Foxglove could not draw it on its image."""
    lines = [json.dumps({"mono_ir": {"timestamp": "2025-07-07 12:52:43.120", "seq": seq,
                                     "label": "crab", "confidence": c}}).encode()
             for seq, c in ((0, 0.9), (0, 0.5), (1, 0.8), (2, 0.7))]
    with Recorder(tmp_path / "early.mcap") as rec:
        rec.add_result(lines[0])  # seq 0's lines before pair 0
        rec.add_result(lines[1])
        rec.add_pair(header(0), jpeg(0, 0), jpeg(0, 1))
        rec.add_result(lines[2])  # seq 1's line; pair 1 never comes (the tap dropped it)
        rec.add_pair(header(2), jpeg(2, 0), jpeg(2, 1))
        rec.add_result(lines[3])  # seq 2's line after its pair, as usual
    got = read_back(tmp_path / "early.mcap")
    recorded = [(t, json.loads(m.data)["mono_ir"])  # type: ignore[attr-defined]
                for t, m in got["/trapflow/results/mono_ir"]]
    assert [(b["seq"], b["confidence"]) for _, b in recorded] == [
        (0, 0.9), (0, 0.5), (1, 0.8), (2, 0.7)]
    left = header(0).t_left_ns - header(0).t_mono_ns
    assert recorded[0][0] == recorded[1][0] == header(0).t_wall_ns + left
    assert recorded[2][0] == 1_751_892_763_120_000_000  # its own timestamp: no pair to take
    assert recorded[3][0] == header(2).t_wall_ns + left
