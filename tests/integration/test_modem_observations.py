"""Observations over the simulated lossy acoustic link: a run's finished tracks and interval
counts reach `trapflow surface` exactly once, with per-pair detections kept on disk
(`modem.detections: false`); a new label reaches the surface before any older per-pair
detection of its interval. The priority order itself is pinned in
tests/unit/test_modem_observations.py, the news' hold on other frames in
tests/unit/test_modem_schedule.py."""

from __future__ import annotations

import calendar
import json
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.conftest import (
    Pipeline,
    modem_cli,
    modem_link,
    only_pools,
    send_until_drained,
    stop_surface,
    write_config,
)
from trapflow.export.check import check_run

pytestmark = pytest.mark.slow  # starts whole pipelines


def _lines(path: Path) -> list[dict]:
    return [json.loads(x) for x in path.read_text().splitlines() if x.strip()]


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_tracks_and_counts_reach_the_surface_exactly_once(
        tmp_path: Path, run_dir: Path, spawn: Callable[..., Pipeline],
        started_procs: list[subprocess.Popen[bytes]]) -> None:
    # A slow link (300 bit/s) that loses one frame in ten.
    modem_link(tmp_path, started_procs, seed=5)
    out = tmp_path / "surface.jsonl"
    surface = modem_cli("surface", str(tmp_path / "b"), "-o", str(out))
    started_procs.append(surface)
    cfg = write_config(tmp_path / "c.yaml", {
        "source": {"width": 640, "height": 360, "rate_hz": 10.0, "seed": 4244},
        "pools": only_pools({"mono": {"count": 1, "policy": "latest"}}),
        "observe": {"interval_s": 5.0, "max_gap_s": 1.0},
        "modem": {"enabled": True, "port": str(tmp_path / "a"), "bit_rate": 300.0,
                  "ack_timeout_s": 1.0, "detections": False},
    })
    p = spawn(["--config", str(cfg), "--duration", "20"], run_dir)
    code, _out, err = p.wait(120)
    assert code == 0, err
    tracks = {t["track"]["id"] for t in _lines(run_dir / "tracks.jsonl")}
    counts = [c["counts"] for c in _lines(run_dir / "counts.jsonl")]
    assert tracks and len(counts) >= 2
    # What the run left in the outbox goes out after it, as a trap's sender does at restart.
    send_until_drained(run_dir / "outbox.sqlite", tmp_path / "a", started_procs, "the outbox")
    stop_surface(surface)

    got = _lines(out)
    kinds = [next(iter(r)) for r in got]
    got_tracks = [r["track"]["id"] for r in got if "track" in r]
    assert sorted(got_tracks) == sorted(tracks)  # every finished track, exactly once
    got_counts = [r["counts"] for r in got if "counts" in r]
    assert len(got_counts) == len(counts)
    assert sum(c["pairs"] for c in got_counts) == sum(c["pairs"] for c in counts)
    assert "mono_ir" not in kinds
    # The modem's counters are in the ledger, none refused as too large (issue 32), and the
    # surface's file tells the run's story.
    modem = json.loads((run_dir / "ledger.json").read_text())["modem"]
    assert modem.get("too_large", 0) == 0 and modem["frames"] > 0, modem
    assert check_run(run_dir, surface=out) == []


def _epoch(stamp: str) -> float:
    """A line's UTC time label ("YYYY-MM-DD HH:MM:SS[.fff]") in seconds."""
    whole = calendar.timegm(time.strptime(stamp[:19], "%Y-%m-%d %H:%M:%S"))
    return whole + (float(stamp[19:]) if len(stamp) > 19 else 0.0)


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_a_new_label_reaches_the_surface_before_older_detections(
        tmp_path: Path, run_dir: Path, spawn: Callable[..., Pipeline],
        started_procs: list[subprocess.Popen[bytes]]) -> None:
    """No surface listens during the run (the box's frames go nowhere, unacknowledged), so
    every record waits in the outbox, detections included; then a lossy link to a surface
    comes up and the box's sender drains the outbox, as at a restart. Each label's first
    track of the run is news: it arrives exactly once, before every per-pair detection of
    its interval older than it, at the capture time of the line that confirmed the track."""
    interval_s = 5.0
    void = tmp_path / "void"
    void.mkdir()
    modem_link(void, started_procs, seed=11)  # the run's link: nobody at its far end
    cfg = write_config(tmp_path / "c.yaml", {
        "source": {"width": 640, "height": 360, "rate_hz": 5.0, "seed": 4244},
        "pools": only_pools({"mono": {"count": 1, "policy": "latest"}}),
        "observe": {"interval_s": interval_s, "max_gap_s": 1.0},
        "modem": {"enabled": True, "port": str(void / "a"), "detections": True,
                  "aggregate": []},  # every detection kept for the surface
    })
    p = spawn(["--config", str(cfg), "--duration", "10"], run_dir)
    code, _out, err = p.wait(120)
    assert code == 0, err
    started_procs[-1].kill()  # that link goes, with whatever it still held
    started_procs[-1].wait(timeout=10)
    lines = [r["mono_ir"] for r in _lines(run_dir / "results.jsonl") if "mono_ir" in r]
    tracks = {t["track"]["id"]: t["track"] for t in _lines(run_dir / "tracks.jsonl")}
    assert tracks, "the run made no track"

    modem_link(tmp_path, started_procs, seed=11)  # one frame in ten lost
    out = tmp_path / "surface.jsonl"
    surface = modem_cli("surface", str(tmp_path / "b"), "-o", str(out))
    started_procs.append(surface)
    send_until_drained(run_dir / "outbox.sqlite", tmp_path / "a", started_procs, "the outbox")
    stop_surface(surface)

    got = _lines(out)
    news = [(i, r["new_label"]) for i, r in enumerate(got) if "new_label" in r]
    labels = [n["label"] for _, n in news]
    assert news and len(set(labels)) == len(labels), labels  # each label once
    # Every track's label was news (a track's label is the one it last carried).
    assert {t["label"] for t in tracks.values()} <= set(labels)
    detections = [(i, r["mono_ir"]) for i, r in enumerate(got)
                  if "mono_ir" in r and r["mono_ir"]["label"] != "none"]
    assert len(detections) == sum(1 for x in lines if x["label"] != "none")
    # `none` lines fit their frames too (issue 32: each was 104 bytes, all refused), so
    # every line of the run reached the surface.
    assert sum("mono_ir" in r for r in got) == len(lines)
    assert json.loads((run_dir / "ledger.json").read_text())["modem"].get("too_large", 0) == 0
    for i, n in news:
        t_news = _epoch(n["time"])
        # The news names the track it is about, at the time its confirming line says.
        assert n["track"] in tracks
        confirming = min((x for x in lines if x.get("track") == n["track"]),
                         key=lambda x: _epoch(x["timestamp"]))
        assert confirming["timestamp"][:19] == n["time"]
        older = [j for j, d in detections
                 if _epoch(d["timestamp"]) < t_news + 1  # news carry whole seconds
                 and _epoch(d["timestamp"]) // interval_s == t_news // interval_s]
        assert older, "no older detection in the news' interval: nothing was tested"
        assert min(older) > i, (n, got[min(older)])
