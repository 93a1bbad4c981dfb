"""Runtime control end to end, with real processes and the real ONNX crab detector:
`trapflow pool` grows and shrinks a pool and moves it between active and inactive (pairs
meanwhile counted as dropped while inactive, none lost), `trapflow param` restarts the pool's
workers with a new parameter, in place when the plugin can be configured again, and the
results change; every change is in status and the
ledger's timeline. And the supervisor speaks sd_notify to a real datagram socket."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from tests.builders import small_source
from tests.conftest import REPO, Pipeline, only_pools, poll_for, write_config

pytestmark = pytest.mark.slow  # starts whole pipelines


def tf(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "trapflow", *args], capture_output=True,
                          text=True, timeout=30, cwd=REPO, check=False)


def pool_stats(p: Pipeline, name: str = "mono") -> dict[str, Any]:
    st = p.status()
    return st["stats"]["pools"][name] if st and st.get("stats") else {}


def node(p: Pipeline, name: str) -> dict[str, Any]:
    st = p.status()
    return next((n for n in st["nodes"] if n["name"] == name), {}) if st else {}


@pytest.mark.timeout(240)
def test_pool_count_lifecycle_and_param_at_run_time(spawn, run_dir: Path) -> None:
    cfg = write_config(run_dir.parent / "ctl.yaml", {
        "source": small_source(4.0, seed=1),
        "pools": only_pools({"mono": {"count": 1, "policy": "latest", "gate": "always"},
                             # a plugin that cannot be configured again: restarted instead
                             "slow": {"plugin": "slow", "params": {"delay_s": 0.05}}}),
    })
    p: Pipeline = spawn(["--config", str(cfg)], run_dir)
    p.wait_active(90)
    rd = ["--run-dir", str(run_dir)]

    # Up: a second worker joins the broker; down: it leaves and is not restarted.
    res = tf("pool", "mono", "--count", "2", *rd)
    assert res.returncode == 0, res.stderr
    assert "count 1 -> 2" in res.stdout
    poll_for(lambda: node(p, "worker:mono:1").get("state") == "active"
             and pool_stats(p).get("workers") == 2, 60, interval=0.3, what="2 mono workers")
    res = tf("pool", "mono", "--count", "1", *rd)
    assert res.returncode == 0, res.stderr
    poll_for(lambda: node(p, "worker:mono:1").get("state") == "finalized"
             and pool_stats(p).get("workers") == 1, 30, interval=0.3, what="back to 1 worker")
    assert node(p, "worker:mono:1")["pid"] is not None

    # Deactivate: pairs are counted as inactive, nothing is processed; a second deactivate
    # is no transition and is refused; activate: processing resumes.
    res = tf("pool", "mono", "--deactivate", *rd)
    assert res.returncode == 0, res.stderr
    poll_for(lambda: pool_stats(p).get("active") is False, 10, what="mono inactive")
    first = pool_stats(p)
    poll_for(lambda: pool_stats(p).get("inactive", 0) >= first["inactive"] + 8, 20,
             interval=0.3, what="pairs counted as inactive")
    later = pool_stats(p)
    assert later["processed"] - first["processed"] <= 1  # at most the one in flight
    refused = tf("pool", "mono", "--deactivate", *rd)
    assert refused.returncode == 1
    assert "ROS 2 lifecycle" in refused.stderr and "inactive" in refused.stderr
    res = tf("pool", "mono", "--activate", *rd)
    assert res.returncode == 0, res.stderr
    poll_for(lambda: pool_stats(p).get("processed", 0) >= later["processed"] + 4, 30,
             interval=0.3, what="processing resumed")

    # A parameter: results with detections before; confidence 1.0 keeps none after.
    # (a result line per detection; one with label "none" for a pair with none)
    poll_for(lambda: any(r["mono_ir"]["label"] != "none" for r in p.results()
                         if "mono_ir" in r),
             60, interval=0.5, what="a detection (crabs walk in after 3 s)")
    mono0 = node(p, "worker:mono:0")
    res = tf("param", "mono", "confidence=1.0", *rd)
    assert res.returncode == 0, res.stderr
    # The crab detector is configured again in place: the same process, no restart.
    assert "param confidence: '(default)' -> 1.0; reconfigured in place" in res.stdout
    mark = len(p.results())
    poll_for(lambda: len([r for r in p.results()[mark:] if "mono_ir" in r]) >= 8, 60,
             interval=0.5, what="8 more mono results")
    after = [r["mono_ir"] for r in p.results()[mark:] if "mono_ir" in r]
    # the first one or two may have been in flight under the old parameters
    assert after[2:] and all(r["label"] == "none" for r in after[2:])
    assert node(p, "worker:mono:0")["pid"] == mono0["pid"]
    assert node(p, "worker:mono:0")["restarts"] == mono0["restarts"]
    # and back: the crabs are still there, so detections return (the change did it)
    assert tf("param", "mono", "confidence=0.25", *rd).returncode == 0
    mark = len(p.results())
    poll_for(lambda: any(r["mono_ir"]["label"] != "none" for r in p.results()[mark:]
                         if "mono_ir" in r), 60, interval=0.5, what="detections again")

    # A plugin without in-place configuration: its worker restarts with the parameter.
    slow0 = node(p, "worker:slow:0")
    res = tf("param", "slow", "delay_s=0.1", *rd)
    assert res.returncode == 0, res.stderr
    assert "restarting workers" in res.stdout
    poll_for(lambda: node(p, "worker:slow:0").get("restarts", 0) > slow0["restarts"]
             and node(p, "worker:slow:0").get("state") == "active", 60, interval=0.3,
             what="the slow worker restarted with the new parameter")
    assert node(p, "worker:slow:0")["pid"] != slow0["pid"]

    # Status shows the pool's control state and the timeline; the ledger keeps it.
    st = p.status()
    assert st is not None
    sup = st["supervision"]
    assert sup["control"] == 7
    assert sup["pools"]["mono"] == {"state": "active", "count": 1, "policy": "latest",
                                    "params": {"confidence": 0.25}, "changes": 6,
                                    "off_by": "", "min_interval_s": 0.0}
    assert sup["pools"]["slow"]["params"] == {"delay_s": 0.1}
    text = tf("status", *rd).stdout
    assert "pool mono" in text and "runtime changes" in text
    assert tf("status", "--stop", *rd).returncode == 0
    code, _out, err = p.wait(60)
    assert code == 0, err
    ledger = json.loads((run_dir / "ledger.json").read_text())
    kinds = [e["kind"] for e in ledger["supervision"]["timeline"]]
    assert kinds.count("control") == 7
    mono = ledger["pools"]["mono"]
    assert mono["dropped_inactive"] >= 8
    assert mono["lost"] == 0


@pytest.mark.timeout(120)
def test_supervisor_sends_ready_watchdog_and_status_to_notify_socket(spawn, run_dir: Path
                                                                     ) -> None:
    """The Type=notify unit's contract: READY=1 once running, then WATCHDOG=1 with the
    status line about once a second, STOPPING=1 at the end."""
    sock_path = run_dir.parent / "notify.sock"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(str(sock_path))
    s.settimeout(60)
    try:
        cfg = write_config(run_dir.parent / "sd.yaml", {
            "source": {"width": 160, "height": 120, "rate_hz": 5.0},
            "pools": only_pools({"fast": {"plugin": "noop", "policy": "latest"}}),
        })
        p: Pipeline = spawn(["--config", str(cfg)], run_dir,
                            env={"NOTIFY_SOCKET": str(sock_path), "WATCHDOG_USEC": "4000000"})
        msgs: list[dict[str, str]] = []

        def take() -> dict[str, str]:
            data = s.recv(4096).decode()
            msgs.append(dict(line.split("=", 1) for line in data.split("\n")))
            return msgs[-1]

        while len([m for m in msgs if "WATCHDOG" in m]) < 3:
            take()
        assert tf("status", "--stop", "--run-dir", str(run_dir)).returncode == 0
        while "STOPPING" not in take():
            pass
        code, _out, err = p.wait(60)
        assert code == 0, err
    finally:
        s.close()
    assert msgs[0]["READY"] == "1" and str(run_dir) in msgs[0]["STATUS"]
    beats = [m for m in msgs if m.get("WATCHDOG") == "1"]
    assert len(beats) >= 3  # one a second while it runs
    assert all("fast" in m["STATUS"] for m in beats)
    assert msgs[-1] == {"STOPPING": "1"}
