"""A wall-clock step in a running pipeline changes only the timestamps written (issue 33).

A trap that boots without a real-time clock gets its time from NTP or GPS later: its wall
clock steps, by an hour or a day. Here every process of a real run (supervisor, capture,
broker, the detector, the normalizer's tracker and counting intervals, the modem sender and
its outbox, health) runs under libfaketime, whose offset file the test rewrites mid-run:
back 1 h, then forward 1 day. The monotonic clock is left alone, as a real step leaves it.
Then the tracks still last what the pairs they span last at the capture rate, counting
intervals keep closing after each step, no record waiting for the slow link expires, every
health record reaches the surface and fits its frame, and the run ends well.

Before (issue 33, the clock stepped back an hour): 27 of 34 tracks lasted 0.0 s, 5 never
ended, no counting interval closed, health said `uptime_s: -775` and 12 of 19 health
records were refused as too large; a day forward, 436 waiting records expired at once.

libfaketime 0.9.10 (Debian's) breaks an absolute sleep on the monotonic clock when it
leaves that clock alone (`FAKETIME_DONT_FAKE_MONOTONIC`): Python 3.11's time.sleep gets
EINVAL. The processes here therefore load a small sitecustomize that sleeps in select()
instead, on the same monotonic deadline; nothing else of the runtime is changed.
"""

from __future__ import annotations

import calendar
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.conftest import Pipeline, modem_cli, modem_link, only_pools, stop_surface, write_config
from trapflow.export.check import check_run

pytestmark = pytest.mark.slow  # starts a whole pipeline

RATE_HZ = 10.0
INTERVAL_S = 2.0  # counting intervals and health records
PHASE_S = 7.0  # run this long before, between and after the steps
BACK_S = -3600  # the wall clock stepped back an hour...
FORWARD_S = BACK_S + 86400  # ...then a day forward

_LIB_DIRS = ("/usr/lib/x86_64-linux-gnu/faketime", "/usr/lib/aarch64-linux-gnu/faketime",
             "/usr/lib/faketime", "/usr/local/lib/faketime", "/usr/lib64/faketime")

# Sleeps in select() until a monotonic deadline (see the module's docstring).
_SITECUSTOMIZE = '''\
import select
import time


def _sleep(secs):
    if secs < 0:
        raise ValueError("sleep length must be non-negative")
    deadline = time.monotonic() + secs
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            return
        select.select([], [], [], left)


time.sleep = _sleep
'''

_PROBE = '''\
import os, sys, time
w0, m0 = time.time(), time.monotonic()
path = sys.argv[1]
with open(path + ".tmp", "w") as f:
    f.write("-3600\\n")
os.replace(path + ".tmp", path)
time.sleep(0.2)
print(time.time() - w0, time.monotonic() - m0)
'''


def _libfaketime() -> Path | None:
    for d in _LIB_DIRS:
        lib = Path(d) / "libfaketime.so.1"
        if lib.exists():
            return lib
    return None


def _set_offset(path: Path, offset_s: int) -> None:
    """Step the wall clock of every process under `path` to real time + offset_s (written
    whole, then renamed: a reader never sees a half-written file)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(f"{offset_s:+d}\n")
    os.replace(tmp, path)


def _faketime_env(tmp: Path) -> tuple[dict[str, str], Path]:
    """The environment that puts a process's wall clock on the offset file (skips without
    libfaketime; fails where it is installed but does not step the wall clock alone)."""
    lib = _libfaketime()
    if lib is None:
        pytest.skip("libfaketime is not installed (Debian: apt-get install faketime)")
    site = tmp / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(_SITECUSTOMIZE)
    offset = tmp / "faketime.rc"
    _set_offset(offset, 0)
    env = {"LD_PRELOAD": str(lib), "FAKETIME_TIMESTAMP_FILE": str(offset),
           "FAKETIME_NO_CACHE": "1", "FAKETIME_DONT_FAKE_MONOTONIC": "1",
           "PYTHONPATH": os.pathsep.join(p for p in (str(site), os.environ.get("PYTHONPATH"))
                                         if p)}
    probe = subprocess.run([sys.executable, "-c", _PROBE, str(offset)], env={**os.environ, **env},
                           capture_output=True, text=True, timeout=30)
    assert probe.returncode == 0, f"libfaketime's probe failed: {probe.stderr}"
    wall, mono = (float(x) for x in probe.stdout.split())
    assert -3610 < wall < -3590 and 0.15 < mono < 5, (
        f"libfaketime did not step the wall clock alone: wall {wall:+.1f} s, "
        f"monotonic {mono:+.2f} s over the probe")
    _set_offset(offset, 0)
    return env, offset


def _epoch(stamp: str) -> float:
    """A UTC time label ("YYYY-MM-DD HH:MM:SS[.fff]") in seconds."""
    whole = calendar.timegm(time.strptime(stamp[:19], "%Y-%m-%d %H:%M:%S"))
    return whole + (float(stamp[19:]) if len(stamp) > 19 else 0.0)


def _lines(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(x) for x in path.read_text().splitlines() if x.strip()]


@pytest.mark.slow
@pytest.mark.timeout(150)
@pytest.mark.unchecked_run("trapflow check runs at the end of the test, where a known "
                           "disagreement is marked")
def test_a_wall_clock_step_changes_only_timestamps(
        tmp_path: Path, run_dir: Path, spawn: Callable[..., Pipeline],
        started_procs: list[subprocess.Popen[bytes]]) -> None:
    env, offset = _faketime_env(tmp_path)
    # A slow link (2400 bit/s) behind 10 detection lines a second: records wait in the
    # outbox across both steps, each with 10 minutes to live, so a time-to-live measured on
    # the wall clock would expire them all at the day's step.
    modem_link(tmp_path, started_procs, seed=7, bit_rate="2400", loss="0")
    surface_out = tmp_path / "surface.jsonl"
    surface = modem_cli("surface", str(tmp_path / "b"), "-o", str(surface_out))
    started_procs.append(surface)
    cfg = write_config(tmp_path / "c.yaml", {
        # Three crabs from the first second: one leaves after about 14 s, one after 21,
        # one stays; so tracks span each step and some end after one.
        "source": {"width": 640, "height": 360, "rate_hz": RATE_HZ, "seed": 11,
                   "options": {"density": 2.0}},
        "pools": only_pools({"mono": {"count": 1, "policy": "fifo:64", "gate": "always"}}),
        "observe": {"interval_s": INTERVAL_S, "max_gap_s": 1.0},
        "modem": {"enabled": True, "port": str(tmp_path / "a"), "bit_rate": 2400.0,
                  "ack_timeout_s": 1.0, "detections": True, "aggregate": [],
                  "ttl_s": {"*": 600.0}},
        "health": {"enabled": True, "interval_s": INTERVAL_S},
    })
    p = spawn(["--config", str(cfg)], run_dir, env=env)
    p.wait_active()
    started = time.monotonic()
    real_start = time.time()  # this process's clock does not step
    time.sleep(PHASE_S)
    _set_offset(offset, BACK_S)
    time.sleep(PHASE_S)
    _set_offset(offset, FORWARD_S)
    time.sleep(PHASE_S)
    code, _out, err = p.stop(signal.SIGINT, timeout=30)
    elapsed = time.monotonic() - started
    assert code == 0, err
    stats = stop_surface(surface)

    def phase(t_s: float) -> int:
        """Which clock named a time: 0 before the steps, 1 an hour back, 2 a day on."""
        return 1 if t_s < real_start - 1800 else 2 if t_s > real_start + 43200 else 0

    # Counting intervals keep closing after each step (2 s each, 7 s a phase).
    counts = [c["counts"] for c in _lines(run_dir / "counts.jsonl")]
    closed = [sum(phase(c["start_s"]) == k for c in counts) for k in range(3)]
    assert min(closed) >= 2, closed

    # Every track lasts what the pairs it spans last at the capture rate, within 10 %
    # (the camera numbers its pairs: seq / rate is the monotonic truth).
    lines = [r["mono_ir"] for r in _lines(run_dir / "results.jsonl") if "mono_ir" in r]
    seqs: dict[int, list[int]] = {}
    for d in lines:
        if d.get("track") is not None:
            seqs.setdefault(d["track"], []).append(d["seq"])
    tracks = {t["track"]["id"]: t["track"] for t in _lines(run_dir / "tracks.jsonl")}
    # None is left open: every track its lines name was written once it ended.
    assert set(seqs) <= set(tracks), sorted(set(seqs) - set(tracks))
    off: list[str] = []
    measured: list[tuple[float, float]] = []
    for tid, t in tracks.items():
        span = seqs.get(tid)
        if not span:
            continue
        # A track's first box (before it was confirmed) has a line that does not name it
        # yet: the pairs may span a pair or so less than the track (hence 1.5 / RATE_HZ).
        truth = (max(span) - min(span)) / RATE_HZ
        measured.append((t["duration_s"], truth))
        if t["pairs"] >= 3:
            assert t["duration_s"] > 0.0, t
        if abs(t["duration_s"] - truth) > max(0.1 * truth, 1.5 / RATE_HZ):
            off.append(f"track {tid}: {t['duration_s']} s, its pairs span {truth:.1f} s")
    assert len(measured) >= 3, f"too few tracks to judge: {len(measured)}"
    assert not off, off
    # Tracks span the steps, and end after one before the run does (a gap measured on the
    # wall clock never closes after a step back).
    named = {d["seq"]: phase(_epoch(d["timestamp"])) for d in lines}
    last_seq = max(named)
    spanning = [tid for tid, sq in seqs.items() if len({named[q] for q in sq}) > 1]
    ended = [tid for tid, sq in seqs.items()
             if named[max(sq)] >= 1 and max(sq) < last_seq - 2 * RATE_HZ]
    assert spanning and ended, (spanning, ended)

    # No record expired early, none was refused as too large; health fits and goes on.
    modem = json.loads((run_dir / "ledger.json").read_text())["modem"]
    assert modem.get("expired", 0) == 0 and modem.get("too_large", 0) == 0, modem
    assert modem["backlog"] > 0, modem  # records did wait across the steps
    health = [r["health"] for r in _lines(surface_out) if "health" in r]
    assert len(health) >= 3, (len(health), stats)
    assert {phase(_epoch(h["timestamp"])) for h in health} == {0, 1, 2}, health
    uptimes = [h["uptime_s"] for h in health]
    assert all(u >= 0 for u in uptimes) and uptimes == sorted(uptimes), uptimes
    assert uptimes[-1] - uptimes[0] <= elapsed + 5, (uptimes, elapsed)

    # Each step said once in the log and kept in the run's timeline.
    ledger = json.loads((run_dir / "ledger.json").read_text())
    assert ledger["supervision"]["clock_steps"] == 2, ledger["supervision"]
    steps = [e["reason"] for e in ledger["supervision"]["timeline"] if e["kind"] == "clock_step"]
    assert len(steps) == 2 and steps[0].startswith("the wall clock stepped by -3")
    assert steps[1].startswith("the wall clock stepped by +86"), steps
    log_text = (run_dir / "trapflow.log").read_text()
    assert log_text.count("the wall clock stepped by") == 2, log_text[-2000:]

    # The run's own duration is the monotonic one.
    run = json.loads((run_dir / "run.json").read_text())
    assert elapsed - 5 <= run["duration_s"] <= elapsed + 30, (run["duration_s"], elapsed)
    print(f"clock step: tracks (duration_s, pairs/rate) {measured}; intervals closed per "
          f"clock {closed}; spanning {spanning}, ended after a step {ended}; modem {modem}; health "
          f"{len(health)} records, uptime {uptimes}; run {run['duration_s']} s of {elapsed:.1f}")

    # `trapflow check`: a track that spans a step is named on the clock after it, while its
    # detection lines keep the clock they were captured on; check holds one against the other.
    told = check_run(run_dir, surface=surface_out)
    if told and spanning:
        pytest.xfail("trapflow check compares a step-spanning track's span (named on the "
                     "clock after the step) with its lines' capture times (on the clock "
                     f"before): {told}")
    assert told == [], told
