"""A power cut keeps the run's memory (issue 33): kill -9 a pipeline's process group while
a track is alive, start it again in the same run directory, and the track of before the cut
is in tracks.jsonl, each track once, and no label's news is given twice.

Regression: over 20 cuts of a run restarting in the same run directory the surface heard
"new label: crab" 21 times, and tracks.jsonl got none of the tracks of the cut cycles."""

from __future__ import annotations

import collections
import json
import os
import signal
import sqlite3
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.conftest import Pipeline, modem_link, only_pools, poll_for, write_config

pytestmark = pytest.mark.slow  # starts whole pipelines


def _lines(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(x) for x in path.read_text().splitlines() if x.strip()]


def _tracked_now(run_dir: Path) -> float | None:
    """The wall time of a line of the newest pairs with a confirmed track, if any."""
    lines = _lines(run_dir / "results.jsonl")[-40:]
    tracked = [x["mono_ir"] for x in lines if x.get("mono_ir", {}).get("track")]
    return time.time() if tracked else None


@pytest.mark.timeout(300)
def test_a_cut_keeps_live_tracks_and_news(tmp_path: Path, run_dir: Path,
                                          spawn: Callable[..., Pipeline],
                                          started_procs: list[subprocess.Popen[bytes]]) -> None:
    modem_link(tmp_path, started_procs, seed=7)
    cfg = write_config(tmp_path / "c.yaml", {
        "source": {"width": 640, "height": 360, "rate_hz": 10.0, "seed": 4244},
        "pools": only_pools({"mono": {"count": 1, "policy": "latest"}}),
        "observe": {"interval_s": 600.0, "max_gap_s": 2.0},
        "modem": {"enabled": True, "port": str(tmp_path / "a"), "bit_rate": 300.0,
                  "detections": False},
    })
    first = spawn(["--config", str(cfg), "--duration", "120"], run_dir)
    first.wait_active(90)
    poll_for(lambda: len(_lines(run_dir / "tracks.jsonl")) >= 1
             and _tracked_now(run_dir), 90, interval=0.2, what="a track ended and one alive")
    first.track()
    cut_s = time.time()
    os.killpg(first.proc.pid, signal.SIGKILL)  # the power cut: the whole process group
    first.proc.wait(10)
    assert not first.leftovers(), "a process outlived the cut"
    before = _lines(run_dir / "tracks.jsonl")
    second = spawn(["--config", str(cfg), "--duration", "15"], run_dir)
    code, _out, err = second.wait(120)
    assert code == 0, err[-3000:]
    tracks = [t["track"] for t in _lines(run_dir / "tracks.jsonl")]
    ids = [t["id"] for t in tracks]
    assert len(ids) == len(set(ids)), f"a track written twice: {ids}"
    # A track alive at the cut was restored and written after it, with its start before.
    after = tracks[len(before):]
    assert any(t["first_s"] < cut_s - 0.5 for t in after), (cut_s, after[:3])
    with sqlite3.connect(run_dir / "outbox.sqlite") as db:
        bodies = [json.loads(b) for (b,) in db.execute("SELECT body FROM records")]
    news = collections.Counter(r["new_label"]["label"] for r in bodies if "new_label" in r)
    assert news and max(news.values()) == 1, news
