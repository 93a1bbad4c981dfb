"""The record command closes its recording cleanly on Ctrl-C (a real recorder process);
the commands' exit codes and one-line errors are in tests/unit/test_sources_cli.py."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import zmq
from rosbags.highlevel import AnyReader

from trapflow.wire.messages import StereoPair, encode
from trapflow.wire.tap_msgs import TOPIC_IMAGE, TOPIC_RESULT


@pytest.mark.timeout(30)
def test_record_command_closes_cleanly_on_ctrl_c(tmp_path: Path) -> None:
    ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context.instance()
    pub = ctx.socket(zmq.XPUB)
    pub.setsockopt(zmq.LINGER, 0)
    endpoint = f"ipc://{tmp_path}/tap.sock"
    pub.bind(endpoint)
    out = tmp_path / "rec.mcap"
    code = ("import sys; from trapflow.cli.sources import record; "
            "record(sys.argv[1:], standalone_mode=True)")
    proc = subprocess.Popen([sys.executable, "-c", code, "--endpoint", endpoint, "-o", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        subscribed: set[bytes] = set()
        while subscribed != {TOPIC_IMAGE, TOPIC_RESULT}:
            assert pub.poll(15000), "recorder never subscribed"
            msg = pub.recv()
            subscribed.add(msg[1:])
        jpg = cv2.imencode(".jpg", np.full((32, 32, 3), 90, np.uint8))[1].tobytes()
        for i in range(5):
            h = StereoPair(seq=i, t_wall_ns=10**18 + i, t_mono_ns=i, t_left_ns=i, t_right_ns=i,
                           skew_ns=0, encoding="jpeg", width=32, height=32)
            pub.send_multipart([TOPIC_IMAGE, encode(h), jpg, jpg])
        assert out.with_name("rec.mcap.part").exists()  # mid-recording: only the .part file
        assert not out.exists()
        proc.send_signal(signal.SIGINT)
        output, _ = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        pub.close(linger=0)
    assert proc.returncode == 0, output
    assert out.is_file() and not out.with_name("rec.mcap.part").exists()
    with AnyReader([out]) as reader:  # opens: summary and footer were written
        n = sum(1 for _ in reader.messages())
    pairs = int(output.split(b"rec.mcap: ")[1].split()[0])
    assert n == 3 * pairs  # left, right and pair header for every pair that arrived
