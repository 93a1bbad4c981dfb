"""Field data as a repeatable test: record a running pipeline to MCAP, replay it losslessly."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from tests.builders import small_source
from tests.conftest import REPO, Pipeline, only_pools, poll_for, record_until, write_config

pytestmark = pytest.mark.slow  # starts whole pipelines


@pytest.mark.timeout(150)
def test_record_then_replay_lossless(spawn, run_dir: Path) -> None:
    work = run_dir.parent
    p: Pipeline = spawn(["--workers", "vo=1", "--size", "320x240", "--rate", "10"], run_dir)
    p.wait_active()
    rec = work / "field.mcap"
    code, err = record_until(run_dir, rec, lambda: len(p.results()) > 40, 30)
    assert code == 0, err
    p.stop(signal.SIGINT)
    with AnyReader([rec]) as reader:  # readable by ROS 2 tooling's library
        topics = {c.topic: c.msgtype for c in reader.connections}
        n_left = sum(1 for c, _, _ in reader.messages()
                     if c.topic == "/trapflow/left/image/compressed")
    assert topics["/trapflow/left/image/compressed"] == "sensor_msgs/msg/CompressedImage"
    assert n_left >= 10
    cfg = write_config(work / "replay.yaml", {
        "source": small_source(None),
        "pools": only_pools({"every": {"plugin": "digest", "policy": "ordered:64"}}),
    })
    replay = subprocess.run(
        [sys.executable, "-m", "trapflow", "replay", str(rec), "--rate", "0", "--assert-lossless",
         "-c", str(cfg), "--workers", "every=1", "--run-dir", str(work / "replayed")],
        cwd=REPO, capture_output=True, text=True, timeout=120)
    assert replay.returncode == 0, replay.stderr + replay.stdout
    assert f"pairs read {n_left}, delivered {n_left}" in replay.stdout
    lines = (work / "replayed" / "results.jsonl").read_text().splitlines()
    assert len(lines) == n_left


@pytest.mark.timeout(150)
def test_recorder_killed_mid_run_leaves_a_part_that_replays(spawn, run_dir: Path) -> None:
    """Regression (issue 12, item 7): a recording killed mid-run left a .part that replay
    rejected although most of its messages were intact. The recorder closes a chunk every
    second, `trapflow recover` keeps every complete message, and replay takes the .part."""
    work = run_dir.parent
    p: Pipeline = spawn(["--workers", "noop=1", "--size", "160x120", "--rate", "10"], run_dir)
    p.wait_active()
    rec = work / "field.mcap"
    part = work / "field.mcap.part"
    recorder = subprocess.Popen(
        [sys.executable, "-m", "trapflow", "record", "--run-dir", str(run_dir), "-o", str(rec)],
        cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        poll_for(lambda: part.exists() and part.stat().st_size > 0, 30,
                 what="the recorder writing")
        time.sleep(4.5)  # about four chunks closed, one in progress
        recorder.kill()  # SIGKILL: no summary, no footer, no rename
        recorder.wait(10)
    finally:
        if recorder.poll() is None:
            recorder.kill()
            recorder.wait(10)
    p.stop(signal.SIGINT)
    assert part.exists() and not rec.exists()
    with pytest.raises(Exception, match="magic|storage format"):  # as it was: unreadable
        AnyReader([part]).open()

    out = subprocess.run([sys.executable, "-m", "trapflow", "recover", str(part)], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert part.exists()  # the input is kept: recovering never writes over it
    assert f"{rec}: " in out.stdout and "messages recovered" in out.stdout
    with AnyReader([rec]) as reader:  # a valid MCAP for ROS 2 tooling's library
        msgs: dict[str, list[bytes]] = {}
        for conn, _, raw in reader.messages():
            if conn.msgtype not in ("sensor_msgs/msg/CompressedImage", "std_msgs/msg/String"):
                continue  # the rig (CameraInfo, tf) and typed results: read elsewhere
            msg = reader.deserialize(raw, conn.msgtype)
            data = bytes(msg.data) if conn.msgtype.endswith("CompressedImage") else \
                msg.data.encode()
            msgs.setdefault(conn.topic, []).append(data)
    left = msgs["/trapflow/left/image/compressed"]
    right = msgs["/trapflow/right/image/compressed"]
    pairs = [json.loads(m) for m in msgs["/trapflow/pairs"]]
    # Chunks close between pairs: whole pairs only, about a second's worth each (10 pairs/s).
    assert len(left) == len(right) == len(pairs) >= 20
    assert [h["seq"] for h in pairs] == list(range(pairs[0]["seq"], pairs[0]["seq"] + len(pairs)))
    for jpg in (*left, *right):  # every image whole: ends with EOI and decodes at full size
        assert jpg.endswith(b"\xff\xd9")
        img = cv2.imdecode(np.frombuffer(jpg, np.uint8), cv2.IMREAD_COLOR)
        assert img is not None and img.shape == (120, 160, 3)

    cfg = write_config(work / "replay.yaml", {
        "pools": {"every": {"plugin": "digest", "policy": "ordered:64"}}})
    replay = subprocess.run(
        [sys.executable, "-m", "trapflow", "replay", str(part), "--rate", "0", "--assert-lossless",
         "-c", str(cfg), "--workers", "every=1", "--size", "160x120",
         "--run-dir", str(work / "replayed")],
        cwd=REPO, capture_output=True, text=True, timeout=120)
    assert replay.returncode == 0, replay.stderr + replay.stdout
    assert "an unfinished recording" in replay.stderr
    assert f"pairs read {len(left)}, delivered {len(left)}" in replay.stdout
    assert len((work / "replayed" / "results.jsonl").read_text().splitlines()) == len(left)
