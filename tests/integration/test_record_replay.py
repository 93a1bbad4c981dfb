"""Field data as a repeatable test: record a running pipeline to MCAP, replay it losslessly."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from tests.builders import small_source
from tests.conftest import (
    REPO,
    Pipeline,
    grown,
    only_pools,
    poll_for,
    record_until,
    write_config,
)

pytestmark = pytest.mark.slow  # starts whole pipelines


@pytest.fixture(scope="module")
def default_recording(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A recording of a run of the default config (mono and stereo behind the motion gate,
    vo) at 320x240 and 10 pairs/s, made once for the module; the pipeline and the recorder
    are gone before the first test that uses it runs, none of their processes left."""
    work = tmp_path_factory.mktemp("default-run")
    p = Pipeline(["--size", "320x240", "--rate", "10"], work / "run")
    try:
        p.wait_active()
        rec = work / "field.mcap"

        def poses() -> int:  # one VO line per pair (a detector writes one per box)
            return sum("stereo_vo" in x for x in p.results())

        code, err = record_until(work / "run", rec, grown(poses, 40), 30)
        assert code == 0, err
        p.stop(signal.SIGINT)
        leaked = p.leftovers()
    finally:
        if p.proc.poll() is None:
            p.stop(signal.SIGTERM, timeout=10)
        p.kill_all()
    assert not leaked, f"processes left behind: {leaked}"
    yield rec


def left_images(rec: Path) -> int:
    with AnyReader([rec]) as reader:  # readable by ROS 2 tooling's library
        return sum(1 for c, _, _ in reader.messages()
                   if c.topic == "/trapflow/left/image/compressed")


def replay_cli(args: list[str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "trapflow", "replay", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=120)


@pytest.mark.timeout(150)
def test_record_then_replay_lossless(default_recording: Path, tmp_path: Path) -> None:
    rec = default_recording
    with AnyReader([rec]) as reader:  # readable by ROS 2 tooling's library
        topics = {c.topic: c.msgtype for c in reader.connections}
    n_left = left_images(rec)
    assert topics["/trapflow/left/image/compressed"] == "sensor_msgs/msg/CompressedImage"
    assert n_left >= 10
    cfg = write_config(tmp_path / "replay.yaml", {
        "source": small_source(None),
        "pools": only_pools({"every": {"plugin": "digest", "policy": "ordered:64"}}),
    })
    replay = replay_cli([str(rec), "--rate", "0", "--assert-lossless", "-c", str(cfg),
                         "--workers", "every=1", "--run-dir", str(tmp_path / "replayed")])
    assert replay.returncode == 0, replay.stderr + replay.stdout
    assert f"pairs read {n_left}, delivered {n_left}" in replay.stdout
    lines = (tmp_path / "replayed" / "results.jsonl").read_text().splitlines()
    assert len(lines) == n_left


@pytest.mark.timeout(240)
def test_a_default_run_replays_every_pair_to_every_pool(default_recording: Path,
                                                        tmp_path: Path) -> None:
    """Regression (issue 32, item 1): a default-config run recorded, then `trapflow replay
    REC --rate 0 --assert-lossless` exited 1 ("pool mono: processed 36 of 193"): the motion
    gate, on by default for mono and stereo, withheld the rest. A replay now feeds every
    pair to every pool; with --gate the gate runs as configured and --assert-lossless
    accounts for what it withheld (processed + gated = read, nothing lost)."""
    rec = default_recording
    n = left_images(rec)
    out = replay_cli([str(rec), "--size", "320x240", "--rate", "0", "--assert-lossless",
                      "--run-dir", str(tmp_path / "all")])
    assert out.returncode == 0, out.stderr + out.stdout
    assert f"pairs read {n}, delivered {n}" in out.stdout
    assert "motion gate on" not in out.stdout
    ledger = json.loads((tmp_path / "all" / "ledger.json").read_text())
    assert {name: p["processed"] for name, p in ledger["pools"].items()} == {
        "mono": n, "stereo": n, "vo": n}
    gated = replay_cli([str(rec), "--size", "320x240", "--rate", "0", "--assert-lossless",
                        "--gate", "--workers", "mono=1", "--run-dir", str(tmp_path / "gated")])
    assert gated.returncode == 0, gated.stderr + gated.stdout
    mono = json.loads((tmp_path / "gated" / "ledger.json").read_text())["pools"]["mono"]
    assert mono["processed"] + mono["gated"] == n and mono["gated"] > 0, mono
    assert f"motion gate on: mono gated {mono['gated']}" in gated.stdout


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
