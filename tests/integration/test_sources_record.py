"""Recording: a real PUB tap feeds record(); the MCAP is read back with rosbags (the
recorder without a tap: tests/unit/test_sources_record.py)."""

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

from tests.builders import TAP_H as H
from tests.builders import TAP_W as W
from tests.builders import read_mcap as read_back
from tests.builders import tap_header as header
from tests.builders import tap_jpeg as jpeg
from tests.builders import tap_result as result
from trapflow.recording.recorder import (
    TOPIC_LEFT,
    TOPIC_PAIRS,
    TOPIC_RIGHT,
    RecordCounts,
    record,
)
from trapflow.wire.messages import encode
from trapflow.wire.tap_msgs import TOPIC_IMAGE, TOPIC_RESULT


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
        # The left at the pair's capture time (its results' timestamp), the right at its skew.
        assert tl == h.t_wall_ns and tr == h.t_wall_ns + (h.t_right_ns - h.t_left_ns)
        stamp = left.header.stamp  # type: ignore[attr-defined]
        assert stamp.sec * 1_000_000_000 + stamp.nanosec == tl
        assert left.format == "jpeg"  # type: ignore[attr-defined]
        assert bytes(left.data) == jpeg(i, 0) and bytes(right.data) == jpeg(i, 1)  # type: ignore[attr-defined]
        img = cv2.imdecode(np.frombuffer(bytes(left.data), np.uint8), cv2.IMREAD_COLOR)  # type: ignore[attr-defined]
        assert img.shape == (H, W, 3)
    for t, msg in got["/trapflow/results/mono_ir"]:
        seq = json.loads(msg.data)["mono_ir"]["seq"]  # type: ignore[attr-defined]
        assert t == header(seq).t_wall_ns  # stamped with its pair's capture time
    meta = [json.loads(m.data) for _, m in got[TOPIC_PAIRS]]  # type: ignore[attr-defined]
    assert [m["seq"] for m in meta] == list(range(n))
