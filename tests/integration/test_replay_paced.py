"""A replay as fast as possible (`--rate 0`) goes at the speed of its slowest pool: capture
waits for the broker instead of the pools dropping pairs, so it is lossless by default."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import REPO, only_pools, write_config
from trapflow.recording.recorder import Recorder
from trapflow.wire.messages import StereoPair

pytestmark = pytest.mark.slow  # starts whole pipelines

W, H = 160, 120
PAIRS = 40
PERIOD_NS = 50_000_000


def write_recording(path: Path, n: int) -> None:
    """A recording of n textured pairs, 20 pairs/s, as `trapflow record` writes them."""
    rng = np.random.default_rng(7)
    with Recorder(path) as rec:
        for i in range(n):
            left = rng.integers(0, 255, (H, W, 3), dtype=np.uint8)
            right = np.roll(left, -4, axis=1)
            t = 10**9 + i * PERIOD_NS
            h = StereoPair(seq=i, t_wall_ns=1_700_000_000_000_000_000 + i * PERIOD_NS,
                           t_mono_ns=t, t_left_ns=t, t_right_ns=t, skew_ns=0,
                           encoding="jpeg", width=W, height=H)
            rec.add_pair(h, cv2.imencode(".jpg", left)[1].tobytes(),
                         cv2.imencode(".jpg", right)[1].tobytes())


@pytest.mark.timeout(180)
def test_replay_at_rate_0_waits_for_the_slowest_pool(tmp_path: Path) -> None:
    """Regression (issue 22, item 2): `trapflow replay --rate 0 --assert-lossless` with the
    default policies dropped most pairs in every pool slower than the file reads (101 pairs:
    mono dropped 62, stereo 83, VO 53) and exited 1. Here a `latest` pool at 20 pairs/s and
    an `ordered:2` pool beside a fast one: every pool must process every pair."""
    rec = tmp_path / "field.mcap"
    write_recording(rec, PAIRS)
    cfg = write_config(tmp_path / "replay.yaml", {"pools": only_pools({
        "slow": {"plugin": "slow", "policy": "latest", "params": {"delay_s": 0.05}},
        "seq": {"plugin": "slow", "policy": "ordered:2", "params": {"delay_s": 0.02}},
        "fast": {"plugin": "noop", "policy": "latest"},
    })})
    run = tmp_path / "replayed"
    replay = subprocess.run(
        [sys.executable, "-m", "trapflow", "replay", str(rec), "--rate", "0",
         "--assert-lossless", "-c", str(cfg), "--workers", "slow=1,seq=1,fast=1",
         "--size", f"{W}x{H}", "--run-dir", str(run)],
        cwd=REPO, capture_output=True, text=True, timeout=150)
    assert replay.returncode == 0, replay.stderr[-3000:] + replay.stdout[-2000:]
    assert f"pairs read {PAIRS}, delivered {PAIRS}" in replay.stdout
    ledger = json.loads((run / "ledger.json").read_text())
    for pool in ("slow", "seq", "fast"):
        counts = ledger["pools"][pool]
        assert counts["processed"] == PAIRS, (pool, counts)
        assert counts["dropped_by_policy"] == 0, (pool, counts)
    assert ledger["dropped_at_capture"] == 0
    # The ordered pool saw every pair in order, no gap reported.
    seen = [json.loads(line)["slow"] for line in (run / "results.jsonl").read_text().splitlines()
            if '"slow"' in line]
    assert len(seen) == 2 * PAIRS and all(s["gap"] == 0 for s in seen)
