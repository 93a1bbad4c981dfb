"""The last leg inside a real pipeline: normalizer -> outbox -> modem node -> simulated
acoustic link -> `trapflow surface`, with health records on the way."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.builders import small_source
from tests.conftest import REPO, Pipeline, only_pools, poll_for, write_config

pytestmark = pytest.mark.slow  # starts whole pipelines


@pytest.fixture
def helpers() -> Iterator[list[subprocess.Popen[bytes]]]:
    started: list[subprocess.Popen[bytes]] = []
    yield started
    for proc in started:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=5)


def _cli(*args: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen([sys.executable, "-m", "trapflow", *args], cwd=REPO,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _lines(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(x) for x in path.read_text().splitlines() if x.endswith("}")]


@pytest.mark.timeout(120)
def test_results_and_health_reach_the_surface(spawn, run_dir: Path, helpers) -> None:
    link = run_dir.parent
    helpers.append(_cli("modem-sim", "--bit-rate", "2400", "--latency", "0.05", "--loss", "0.05",
                        "--seed", "3", "--link-a", str(link / "a"), "--link-b", str(link / "b")))
    poll_for(lambda: (link / "a").exists() and (link / "b").exists(), 20, what="the ptys")
    surface_out = link / "surface.jsonl"
    helpers.append(_cli("surface", str(link / "b"), "-o", str(surface_out)))
    cfg = write_config(link / "modem.yaml", {
        "source": small_source(5.0),
        "pools": only_pools({"stereo": {"plugin": "histogram", "policy": "latest",
                                        "gate": "always"}}),
        "modem": {"enabled": True, "port": str(link / "a"), "bit_rate": 2400.0,
                  "ack_timeout_s": 1.0, "reopen_interval_s": 0.5},
        "health": {"enabled": True, "interval_s": 2.0},
    })
    p: Pipeline = spawn(["--config", str(cfg)], run_dir)
    st = p.wait_active()
    assert any(n["name"] == "modem" for n in st["nodes"])

    def arrived() -> list[dict] | None:
        got = _lines(surface_out)
        with_pools = [r for r in got if "health" in r and "stereo" in json.dumps(r)]
        return got if with_pools and len(got) >= 8 else None

    got = poll_for(arrived, 60, interval=0.5, what="results and health at the surface")
    code, _, err = p.stop(signal.SIGINT)
    assert code == 0, err
    local = {r["stereo_ir"]["seq"]: r["stereo_ir"] for r in _lines(run_dir / "results.jsonl")}
    received = [r["stereo_ir"] for r in got if "stereo_ir" in r]
    seqs = [r["seq"] for r in received]
    assert len(seqs) == len(set(seqs))  # exactly once
    for r in received:  # the JSON shape survives the compact link encoding
        assert r["seq"] in local and r["label"] == local[r["seq"]]["label"]
        assert r["timestamp"] == local[r["seq"]]["timestamp"]
        assert abs(r["confidence"] - local[r["seq"]]["confidence"]) <= 0.01
    health = [r["health"] for r in got if "health" in r]
    assert all("cpu_pct" in h and "disk_free_mb" in h for h in health)
