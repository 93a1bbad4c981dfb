"""The degradation ladder end to end, with real processes and the real ONNX scallop
classifier: a fake CPU temperature (a file, in millidegrees as sysfs gives it) goes hot, the
ladder steps to ir_slowed and the stereo pool gets at most one pair per K s (the others
counted as dropped by the level); it cools, the ladder comes back to full and the pool to
its rate; status, the status model and the ledger's timeline show both changes, and
`trapflow level` forces a level and gives it back to the triggers."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from tests.builders import small_source
from tests.conftest import REPO, Pipeline, only_pools, poll_for, write_config
from trapflow.cli.status_text import format_status
from trapflow.wire import control_client as control
from trapflow.wire import control_msgs

pytestmark = pytest.mark.slow  # starts whole pipelines

K = 1.0  # the stereo pool's minimum interval at ir_slowed, seconds
WINDOW = 2.5  # seconds the pool's rate is measured over at each level


def tf(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "trapflow", *args], capture_output=True,
                          text=True, timeout=30, cwd=REPO, check=False)


def stereo(p: Pipeline) -> tuple[float, dict[str, Any], dict[str, Any]]:
    """The broker's uptime, the stereo pool's counters and the ladder's view, one status
    (asked on the control socket from here: a `trapflow status` process costs a second)."""
    st = control.request(p.run_dir, "status", timeout_s=10.0)
    assert st.get("stats"), f"no stats in status: {st}"
    return st["stats"]["uptime_s"], st["stats"]["pools"]["stereo"], \
        st["supervision"]["ladder"]


def processed_over(p: Pipeline, seconds: float) -> tuple[int, float, dict[str, Any]]:
    """Pairs the stereo pool processed over about `seconds` of the broker's clock."""
    t0, s0, _ = stereo(p)
    poll_for(lambda: stereo(p)[0] >= t0 + seconds, seconds + 20, interval=0.2,
             what=f"{seconds} s of stats")
    t1, s1, lad = stereo(p)
    return s1["processed"] - s0["processed"], t1 - t0, {**s1, "ladder": lad}


@pytest.mark.timeout(120)
def test_hot_cpu_slows_stereo_and_it_comes_back(spawn, run_dir: Path) -> None:
    temp = run_dir.parent / "thermal_zone0_temp"
    temp.write_text("40000\n")
    cfg = write_config(run_dir.parent / "ladder.yaml", {
        "source": small_source(8.0, seed=1),
        "pools": only_pools({"stereo": {"count": 1, "policy": "latest", "gate": "always"}}),
        "ladder": {
            "interval_s": 0.2,
            "levels": [{"name": "full"},
                       {"name": "ir_slowed", "pools": {"stereo": {"min_interval_s": K}}}],
            "triggers": [{"sensor": "cpu_temp_c", "enter": {"ir_slowed": 80.0},
                          "release": {"ir_slowed": 75.0}, "dwell_s": 0.4}],
            "sensors": {"temperature_path": str(temp), "temperature_unit": "mC"},
        },
    })
    p: Pipeline = spawn(["--config", str(cfg)], run_dir)
    st = p.wait_active(90)
    assert st["supervision"]["ladder"]["level"] == "full"

    full_n, full_dt, _ = processed_over(p, WINDOW)
    assert full_n > full_dt / K + 1, f"stereo at full: {full_n} pairs in {full_dt:.1f} s"

    temp.write_text("85000\n")  # hot
    # The broker's stats say it applies the interval: counted from there on.
    poll_for(lambda: stereo(p)[1]["min_interval_s"] == K, 20, interval=0.2,
             what="the ladder at ir_slowed, the broker applying it")
    slow_n, slow_dt, s = processed_over(p, WINDOW)
    # One pair per K s: the pair at the window's start may be the one before it.
    assert slow_n <= slow_dt / K + 1, f"stereo slowed: {slow_n} pairs in {slow_dt:.1f} s"
    assert s["throttled"] > 0 and s["min_interval_s"] == K and s["ladder"]["level"] == \
        "ir_slowed"
    assert "cpu_temp_c 85C >= 80C" in s["ladder"]["reason"]

    text = format_status(control.request(run_dir, "status"))  # `trapflow status`
    assert "ladder: level ir_slowed (1 of 1, auto)" in text
    assert "at most 1 pair / 1 s" in text

    temp.write_text("40000\n")  # cool again
    poll_for(lambda: stereo(p)[1]["min_interval_s"] == 0.0, 20, interval=0.2,
             what="the ladder back at full, the broker applying it")
    back_n, back_dt, s = processed_over(p, WINDOW)
    assert back_n > back_dt / K + 1, f"stereo back at full: {back_n} pairs in {back_dt:.1f} s"
    assert s["min_interval_s"] == 0.0 and s["ladder"]["level"] == "full"

    # The operator forces a level, then gives it back to the triggers.
    res = tf("level", "ir_slowed", "--run-dir", str(run_dir))
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith("level ir_slowed (forced): full -> ir_slowed: forced")
    assert "unknown level 'warm'" in control.request(
        run_dir, control_msgs.LevelRequest(level="warm"))["error"]
    res = tf("level", "auto", "--run-dir", str(run_dir), "--json")
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout) == {"level": "ir_slowed", "auto": True,
                                      "reason": "auto (from ir_slowed)"}
    poll_for(lambda: stereo(p)[2]["level"] == "full", 20, interval=0.2,
             what="auto: cool, back to full")

    code, out, err = p.stop()
    assert code == 0, err
    ledger = json.loads((run_dir / "ledger.json").read_text())
    levels = [e["reason"] for e in ledger["supervision"]["timeline"] if e["kind"] == "level"]
    assert levels[0].startswith("full -> ir_slowed: cpu_temp_c 85C >= 80C")
    assert levels[1].startswith("ir_slowed -> full: cpu_temp_c 40C < 75C")
    assert levels[2] == "full -> ir_slowed: forced by the operator"
    lad = ledger["supervision"]["ladder"]
    assert lad["changes"] == 4 and lad["level"] == "full"
    pool = ledger["pools"]["stereo"]
    assert pool["dropped_by_level"] > 0 and pool["lost"] == 0
    log = (run_dir / "trapflow.log").read_text()
    assert log.count("ladder: level ") >= 4
