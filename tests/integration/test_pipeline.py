"""End to end with real processes: start, results from every pool, tap, status, clean stop."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

import psutil
import pytest

from tests.builders import small_source
from tests.conftest import REPO, Pipeline, only_pools, poll_for

pytestmark = pytest.mark.slow  # starts whole pipelines

SMALL = ["--size", "320x240", "--rate", "15"]


@pytest.mark.timeout(90)
def test_start_runs_every_pool_writes_results_and_sigterm_stops_everything_within_5s(
        spawn, run_dir: Path) -> None:
    """Every pool answers, in order where its policy says so; then SIGTERM (systemd's stop)
    ends every process within 5 s with exit 0 and nothing left (one pipeline for both: the
    stop is the last thing the scenario does)."""
    p: Pipeline = spawn(["--workers", "mono=2,stereo=1,vo=1", *SMALL], run_dir)
    p.wait_active()
    kids = p.track()
    assert len(kids) >= 6
    poll_for(lambda: len({r.get("stereo_vo", {}).get("seq") for r in p.results()}) > 30, 60,
             what="30 pairs through VO")
    t0 = time.monotonic()
    code, out, err = p.stop(signal.SIGTERM, timeout=10)
    assert time.monotonic() - t0 < 5.0
    assert code == 0, err
    assert f"run directory: {run_dir}" in out
    assert "totals:" in out and "mono 2w" in out
    rows = p.results()
    by_pool: dict[str, list[int]] = defaultdict(list)
    for row in rows:
        (key, body), = row.items()
        assert isinstance(body["seq"], int) and isinstance(body["timestamp"], str)
        by_pool[key].append(body["seq"])
    assert set(by_pool) == {"mono_ir", "stereo_ir", "stereo_vo"}
    produced = max(max(s) for s in by_pool.values()) + 1
    assert produced >= 30  # about 15 pairs/s for several seconds
    vo = by_pool["stereo_vo"]
    assert vo == sorted(vo) and len(vo) == len(set(vo))  # ordered pool: in order, once each
    assert len(set(by_pool["stereo_ir"])) == len(by_pool["stereo_ir"])
    assert all(0 <= s < produced for seqs in by_pool.values() for s in seqs)
    assert not p.leftovers()


@pytest.mark.timeout(90)
def test_tap_and_status_attach_then_the_supervisor_killed_leaves_no_orphans(
        spawn, run_dir: Path) -> None:
    """Regression: with raw frames in the ring by default, `tap --save-frames` wrote the raw
    bytes (.bgr); it saves JPEG photos, encoding a raw pair once. Then the supervisor is
    killed (kill -9) and no node outlives it (one pipeline for both)."""
    p: Pipeline = spawn(["--workers", "mono=1,vo=1", *SMALL], run_dir)
    def all_active() -> dict | None:
        s = p.status()
        if s and s.get("stats") and all(n["state"] == "active" for n in s["nodes"]):
            return s
        return None

    status = poll_for(all_active, 40, what="every node active")
    names = {n["name"]: n for n in status["nodes"]}
    assert set(names) >= {"capture", "broker", "normalizer", "worker:mono:0", "worker:vo:0"}
    assert status["ring"]["slots"] > 0 and status["ring"]["held"] <= status["ring"]["slots"]
    poll_for(lambda: (s := p.status()) and s["stats"]["pools"]["vo"]["received"] > 0, 10,
             what="pairs reaching the vo pool")
    tap = subprocess.run(
        [sys.executable, "-m", "trapflow", "tap", "all", "--count", "60", "--timeout", "30",
         "--run-dir", str(run_dir)], capture_output=True, text=True, timeout=50, cwd=REPO)
    assert tap.returncode == 0, tap.stderr
    lines = tap.stdout.splitlines()
    assert len(lines) == 60
    kinds = {line.split()[0] for line in lines}
    assert {"frame", "result"} <= kinds
    saved = run_dir.parent / "frames"
    tap = subprocess.run(
        [sys.executable, "-m", "trapflow", "tap", "frames", "--count", "2", "--timeout", "20",
         "--save-frames", str(saved), "--run-dir", str(run_dir)],
        capture_output=True, text=True, timeout=40, cwd=REPO)
    assert tap.returncode == 0, tap.stderr
    import cv2

    jpgs = sorted(saved.glob("*_left.jpg"))
    assert len(jpgs) == 2 and cv2.imread(str(jpgs[0])).shape == (240, 320, 3)
    # The nodes' fork server listens beside the run's sockets, not in a folder of the
    # system's temporary directory that a kill -9 would leave behind.
    assert [f for f in run_dir.iterdir() if f.name.startswith("listener-") and f.is_socket()]
    # Last, the supervisor killed (kill -9): no node outlives it.
    kids = p.track()
    p.proc.kill()
    p.proc.wait(5)
    _gone, alive = psutil.wait_procs(kids, timeout=5)
    assert not alive, [k.pid for k in alive]


@pytest.mark.timeout(60)
def test_save_flag_keeps_debug_pairs(spawn, run_dir: Path) -> None:
    from tests.conftest import write_config

    cfg = write_config(run_dir.parent / "save.yaml", {
        "source": small_source(10.0),
        "pools": only_pools({"stereo": {"plugin": "histogram", "save": True, "time": True}}),
    })
    p: Pipeline = spawn(["--config", str(cfg), "--duration", "5"], run_dir)
    code, _, err = p.wait(45)
    assert code == 0, err
    folders = list((run_dir / "debug").iterdir())
    assert len(folders) == 1 and folders[0].name.startswith("stereo-0-")
    saved = sorted(folders[0].glob("*.json"))
    assert 1 <= len(saved) <= 6  # rate limited to about one per second
    import cv2

    assert cv2.imread(str(saved[0]).replace(".json", "_left.jpg")).shape == (240, 320, 3)
    assert "stereo_ir" in saved[0].read_text()
    assert "pair 0 in" in (run_dir / "trapflow.log").read_text()  # `time: true` logs timings
