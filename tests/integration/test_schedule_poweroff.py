"""`trapflow start` with a schedule of short windows and `between: poweroff` (issue 33): the
run records inside its window, stops in order at its end (exit 0, a normal ledger), sets
the wake alarm for the next window less the boot margin and runs the poweroff command. The
alarm is a temporary file and the poweroff a command that records it ran."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.builders import small_source
from tests.conftest import REPO, only_pools, write_config

EVERY_S = 60.0
FOR_S = 15.0
LEAD_S = 2.0  # the window begins this long after the test computes it
BOOT_MARGIN_S = 5.0


@pytest.mark.timeout(90)
def test_a_window_ends_in_order_then_the_alarm_and_the_poweroff(run_dir: Path) -> None:
    tmp = run_dir.parent
    off_log = tmp / "poweroff.log"
    off = tmp / "poweroff.py"
    off.write_text(f"open({str(off_log)!r}, 'a').write('off\\n')\n")
    start = time.time() + LEAD_S
    offset_s = start % EVERY_S
    cfg = write_config(tmp / "c.yaml", {
        "source": small_source(10.0),
        "pools": only_pools({"d": {"plugin": "digest"}}),
        "schedule": {"every_min": EVERY_S / 60, "for_min": FOR_S / 60,
                     "offset_min": offset_s / 60, "between": "poweroff"},
        "power": {"wake": "rtc", "rtc_path": str(tmp / "wakealarm"),
                  "boot_margin_s": BOOT_MARGIN_S, "min_off_s": 10.0,
                  "poweroff_command": f"{sys.executable} {off}"}})
    path = os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)
    t0 = time.monotonic()
    out = subprocess.run(
        [sys.executable, "-m", "trapflow", "start", "--config", str(cfg), "--run-dir",
         str(run_dir)], cwd=tmp, env={**os.environ, "PYTHONPATH": path},
        capture_output=True, text=True, timeout=70)
    took = time.monotonic() - t0
    assert out.returncode == 0, out.stderr
    # It stopped at the window's end: not before, and not long after (the stop ladder).
    assert time.time() >= start + FOR_S - 1.0 and took < LEAD_S + FOR_S + 25, took
    assert "recording window until" in out.stdout
    assert "powering off" in out.stdout
    ledger = json.loads((run_dir / "ledger.json").read_text())
    assert ledger["produced"] > 0
    assert ledger["pools"]["d"]["lost"] == 0
    assert (run_dir / "results.jsonl").read_text().count("\n") > 0
    # The alarm: the next window's start less the boot margin, written after a 0.
    next_start = start + EVERY_S
    assert int((tmp / "wakealarm").read_text()) == pytest.approx(
        next_start - BOOT_MARGIN_S, abs=1.0)
    assert off_log.read_text() == "off\n"
