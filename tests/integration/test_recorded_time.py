"""Re-analysis of a recording keeps its capture times: `trapflow process` and `trapflow replay`
label each pair's results with the time the recording gives that pair."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from rosbags.highlevel import AnyReader

from tests.conftest import (
    REPO,
    Pipeline,
    only_pools,
    read_lines,
    record_until,
    run_process,
    write_config,
)
from trapflow.normalizer.result_json import timestamp

LEFT = "/trapflow/left/image/compressed"


def _recorded(rec: Path) -> tuple[list[int], list[int]]:
    """The left images' capture stamps in ns, in order, and the live seq of each pair."""
    stamps: list[int] = []
    seqs: list[int] = []
    with AnyReader([rec]) as reader:
        for conn, _t, raw in reader.messages():
            if conn.topic == LEFT:
                stamp = reader.deserialize(raw, conn.msgtype).header.stamp
                stamps.append(stamp.sec * 1_000_000_000 + stamp.nanosec)
            elif conn.topic == "/trapflow/pairs":
                seqs.append(json.loads(reader.deserialize(raw, conn.msgtype).data)["seq"])
    return stamps, seqs


def _times(lines: list[dict[str, Any]]) -> dict[int, str]:
    return {body["seq"]: body["timestamp"] for line in lines for body in line.values()}


@pytest.mark.timeout(240)
def test_process_and_replay_label_results_with_the_recorded_capture_times(
        spawn, run_dir: Path) -> None:
    """Regression (issue 22, item 3): `trapflow process` on a recording stamped results with
    the file's modification time plus position x rate (none equal to the live run's, 59 s
    off), and `trapflow replay` with the replay's own wall clock. Issue 32: both now carry
    exactly the live run's `timestamp` for the same pair."""
    work = run_dir.parent
    cfg = write_config(work / "c.yaml", {
        "source": {"width": 160, "height": 120},
        "pools": only_pools({"d": {"plugin": "digest", "policy": "ordered:64"}})})
    p: Pipeline = spawn(["--config", str(cfg), "--rate", "10"], run_dir)
    p.wait_active()
    rec = work / "field.mcap"
    part = work / "field.mcap.part"
    since: list[int] = []  # results written when the recorder had begun

    def recorded_enough() -> bool:
        if not since and part.exists() and part.stat().st_size > 0:
            since.append(len(p.results()))
        return bool(since) and len(p.results()) > since[0] + 15

    code, err = record_until(run_dir, rec, recorded_enough, 60)
    assert code == 0, err
    p.stop(signal.SIGINT)
    live = _times(p.results())
    stamps, seqs = _recorded(rec)
    assert len(stamps) == len(seqs) >= 5

    code, _out, err = run_process([str(rec), "--config", str(cfg), "--workers", "d",
                                   "--out", str(work / "processed"), "--local", "1"])
    assert code == 0, err
    replay = subprocess.run(
        [sys.executable, "-m", "trapflow", "replay", str(rec), "--rate", "0", "-c", str(cfg),
         "--run-dir", str(work / "replayed")],
        cwd=REPO, capture_output=True, text=True, timeout=120)
    assert replay.returncode == 0, replay.stderr + replay.stdout

    want = {i: timestamp(t) for i, t in enumerate(stamps)}
    processed = _times(read_lines(work / "processed" / "field.mcap" / "results.jsonl"))
    replayed = _times(read_lines(work / "replayed" / "results.jsonl"))
    assert processed == want
    assert replayed == want
    # The live run labelled the same pairs with the same times, to the millisecond (issue
    # 32: the left image's own stamp was 1-58 ms off the live label for 188 of 193 pairs).
    same = [seq for i, seq in enumerate(seqs) if seq in live and live[seq] == want[i]]
    both = [seq for seq in seqs if seq in live]
    assert both and len(same) == len(both), [(s, live[s]) for s in both if s not in same]
    # One command says the same: both re-analyses tell the live run's story.
    for other in (work / "replayed", work / "processed" / "field.mcap"):
        res = subprocess.run(
            [sys.executable, "-m", "trapflow", "check", str(run_dir), "--config", str(cfg),
             "--against", str(other)], cwd=REPO, capture_output=True, text=True, timeout=60)
        assert res.returncode == 0, res.stdout + res.stderr
        assert f"of the {len(stamps)} pairs" in res.stderr and "tells its story" in res.stdout

