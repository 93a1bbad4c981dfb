"""Field data as a repeatable test: record a running pipeline to MCAP, replay it losslessly."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest
from rosbags.highlevel import AnyReader

from tests.conftest import REPO, Pipeline, only_pools, poll_for, write_config


@pytest.mark.timeout(150)
def test_record_then_replay_lossless(spawn, run_dir: Path) -> None:
    work = run_dir.parent
    p: Pipeline = spawn(["--workers", "vo=1", "--size", "320x240", "--rate", "10"], run_dir)
    p.wait_active()
    rec = work / "field.mcap"
    recorder = subprocess.Popen(
        [sys.executable, "-m", "trapflow", "record", "--run-dir", str(run_dir), "-o", str(rec)],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        poll_for(lambda: len(p.results()) > 40, 30, what="pairs flowing while recording")
    finally:
        recorder.send_signal(signal.SIGINT)
        out, err = recorder.communicate(timeout=20)
    assert recorder.returncode == 0, err
    p.stop(signal.SIGINT)
    with AnyReader([rec]) as reader:  # readable by ROS 2 tooling's library
        topics = {c.topic: c.msgtype for c in reader.connections}
        n_left = sum(1 for c, _, _ in reader.messages()
                     if c.topic == "/trapflow/left/image/compressed")
    assert topics["/trapflow/left/image/compressed"] == "sensor_msgs/msg/CompressedImage"
    assert n_left >= 10
    cfg = write_config(work / "replay.yaml", {
        "source": {"width": 320, "height": 240},
        "pools": only_pools({"every": {"plugin": "digest", "policy": "ordered:64"}}),
    })
    replay = subprocess.run(
        [sys.executable, "-m", "trapflow", "replay", str(rec), "--rate", "0", "--assert-lossless",
         "-c", str(cfg), "--run-dir", str(work / "replayed")],
        cwd=REPO, capture_output=True, text=True, timeout=120)
    assert replay.returncode == 0, replay.stderr + replay.stdout
    assert f"pairs read {n_left}, delivered {n_left}" in replay.stdout
    lines = (work / "replayed" / "results.jsonl").read_text().splitlines()
    assert len(lines) == n_left
