"""The modem path without hardware: outbox -> sender -> simulator (ptys) -> `trapflow surface`.

The simulator and the surface run as real processes through the CLI; the sender runs in
a thread here so its configuration and counters are at hand.
"""

from __future__ import annotations

import collections
import json
import signal
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import modem_cli, poll_for, run_sender_until
from trapflow.config.modem import ModemConfig, OutboxConfig
from trapflow.modem.outbox import Outbox
from trapflow.modem.sender import ModemSender


def stop(proc: subprocess.Popen[bytes]) -> dict[str, Any]:
    """SIGTERM, wait, and return the stats line the command prints on exit."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=10)
    lines = err.decode().strip().splitlines()
    return json.loads(lines[-1]) if lines and lines[-1].startswith("{") else {}


def start_sim(
    tmp: Path, started_procs: list[subprocess.Popen[bytes]], *opts: str
) -> subprocess.Popen[bytes]:
    (tmp / "a").unlink(missing_ok=True)
    sim = modem_cli("modem-sim", *opts, "--link-a", str(tmp / "a"), "--link-b", str(tmp / "b"))
    started_procs.append(sim)
    poll_for(lambda: (tmp / "a").exists() and (tmp / "b").exists(), 20, what="the simulator's ends")
    return sim


def lines_of(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.endswith("}")]


def ts(i: int) -> str:
    return f"2025-07-07 12:{i // 60:02d}:{i % 60:02d}.{i * 7 % 1000:03d}"


@pytest.mark.timeout(120)
def test_300_bits_10_percent_loss(
        tmp_path: Path, started_procs: list[subprocess.Popen[bytes]]) -> None:
    """Scallops arrive once and in order; crabs are summarised; odometry expires; budget kept."""
    start_sim(tmp_path, started_procs, "--bit-rate", "300", "--latency", "0.3", "--loss", "0.1",
              "--noise", "0.1", "--seed", "7")  # fmt: skip
    out = tmp_path / "surface.jsonl"
    surface = modem_cli("surface", str(tmp_path / "b"), "-o", str(out))
    started_procs.append(surface)

    box = Outbox(tmp_path / "outbox.sqlite", OutboxConfig())
    scallops = 8
    for i in range(40):
        rec = {"timestamp": ts(i), "seq": i, "label": "crab", "confidence": round(0.3 + i / 100, 2),
               "box": [10.0 + i, 20.0, 60.5, 80.25]}  # fmt: skip
        box.append({"mono_ir": rec})
        box.append({"stereo_vo": {"timestamp": ts(i), "seq": i, "ok": True,
                                  "Rt": [[1.0, 0.0, 0.0, 0.01], [0.0, 1.0, 0.0, 0.0],
                                         [0.0, 0.0, 1.0, 0.1]], "inliers": 100 + i}})  # fmt: skip
        if i % 5 == 0:
            box.append({"stereo_ir": {"timestamp": ts(i), "seq": i, "label": "scallop",
                                      "confidence": 0.9}})  # fmt: skip
    appended_at = time.time()
    # Aggregation summarises whole intervals only: let the 1 s interval of these records end.
    poll_for(lambda: int(time.time()) > int(appended_at), 2, what="the interval to end")

    cfg = ModemConfig(enabled=True, port=str(tmp_path / "a"), bit_rate=300.0,
                      bytes_per_hour=3000, ack_timeout_s=1.5, ttl_s={"stereo_vo": 3.0},
                      aggregate=["mono_ir/*"], aggregate_interval_s=1.0, aggregate_backlog=4,
                      reopen_interval_s=0.5)  # fmt: skip
    elapsed, stats = run_sender_until(tmp_path / "outbox.sqlite", cfg,
                                      lambda: box.counts()[2] == 0, 90, "the outbox to drain")
    surface_stats = stop(surface)
    sim_stats = stop(started_procs[0])
    got = lines_of(out)
    per_class: dict[str, list[dict[str, Any]]] = collections.defaultdict(list)
    for rec in got:
        key, body = next(iter(rec.items()))
        per_class[body["class"] if key == "aggregate" else f"{key}/{body.get('label', '')}"].append(
            rec
        )

    # Every scallop exactly once, in order, first (highest priority).
    sc = [r["stereo_ir"]["seq"] for r in per_class["stereo_ir/scallop"]]
    assert sc == [0, 5, 10, 15, 20, 25, 30, 35][:scallops]
    assert next(iter(got[0])) == "stereo_ir"
    assert per_class["stereo_ir/scallop"][0] == {
        "stereo_ir": {"timestamp": ts(0), "seq": 0, "label": "scallop", "confidence": 0.9}
    }
    # Crabs: sent one by one or counted in an aggregate, never both, never twice.
    singles = [r["mono_ir"]["seq"] for r in per_class["mono_ir/crab"] if "mono_ir" in r]
    aggs = [r["aggregate"] for r in per_class["mono_ir/crab"] if "aggregate" in r]
    assert aggs, "the link was behind: crabs should have been summarised"
    assert len(singles) == len(set(singles))
    assert len(singles) + sum(a["count"] for a in aggs) == 40
    for agg in aggs:
        assert agg["best"] and agg["from"] <= agg["to"]
        best = [b["mono_ir"]["confidence"] for b in agg["best"]]
        assert best == sorted(best, reverse=True)
    # Odometry is last in priority with a 3 s TTL: what did not go expired.
    vo = [r for r in got if "stereo_vo" in r]
    assert stats["expired"] > 0 and len(vo) + stats["expired"] == 40
    # The link: losses and noise happened, were retransmitted / discarded, budget and rate kept.
    assert sim_stats["a->b"]["lost"] > 0 and stats["retransmits"] > 0
    assert surface_stats["link"]["garbage_bytes"] > 0 and surface_stats["undecodable"] == 0
    assert stats["bytes"] <= cfg.bytes_per_hour
    assert stats["bytes"] * 10 / cfg.bit_rate <= elapsed + 4  # one frame of slack
    print(f"sender {stats}\nsurface {surface_stats}\nsim {sim_stats}\nelapsed {elapsed:.1f}s")
    box.close()


@pytest.mark.timeout(90)
def test_port_disappears_and_comes_back(
    tmp_path: Path, started_procs: list[subprocess.Popen[bytes]]
) -> None:
    """The sink goes inactive with a reason, the outbox keeps filling, sending resumes."""
    fast = ("--bit-rate", "19200", "--latency", "0.02")
    sim = start_sim(tmp_path, started_procs, *fast)
    out = tmp_path / "surface.jsonl"
    surface = modem_cli("surface", str(tmp_path / "b"), "-o", str(out))
    started_procs.append(surface)
    box = Outbox(tmp_path / "outbox.sqlite", OutboxConfig())
    cfg = ModemConfig(bit_rate=19200.0, ack_timeout_s=0.3, reopen_interval_s=0.2)
    sender = ModemSender(tmp_path / "outbox.sqlite", str(tmp_path / "a"), cfg)
    halt = threading.Event()
    thread = threading.Thread(target=sender.run, args=(halt,))
    thread.start()

    def scallop(i: int) -> dict[str, Any]:
        return {"stereo_ir": {"timestamp": ts(i), "seq": i, "label": "scallop", "confidence": 0.8}}

    try:
        for i in range(5):
            box.append(scallop(i))
        poll_for(lambda: len(lines_of(out)) == 5, 30, what="the first records at the surface")
        poll_for(lambda: box.counts()[2] == 0, 10, what="their acknowledgements")
        stop(sim)
        started_procs.remove(sim)
        poll_for(lambda: sender.stats()["state"] == "inactive", 10, what="the sender to notice")
        assert str(tmp_path / "a") in sender.stats()["reason"]
        for i in range(5, 12):
            box.append(scallop(i))
        assert box.counts()[2] == 7
        start_sim(tmp_path, started_procs, *fast)
        poll_for(lambda: box.counts()[2] == 0, 30, what="sending to resume")
        poll_for(lambda: len(lines_of(out)) == 12, 10, what="the rest at the surface")
    finally:
        halt.set()
        thread.join(timeout=10)
    assert [r["stereo_ir"]["seq"] for r in lines_of(out)] == list(range(12))
    assert sender.port.opens == 2
    stop(surface)
    box.close()
