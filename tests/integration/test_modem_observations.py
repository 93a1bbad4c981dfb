"""Observations over the simulated lossy acoustic link: a run's finished tracks and interval
counts reach `trapflow surface` exactly once, with per-pair detections kept on disk
(`modem.detections: false`). That they overtake queued detections is the outbox's priority
order, pinned in tests/unit/test_modem_observations.py."""

from __future__ import annotations

import json
import subprocess
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
