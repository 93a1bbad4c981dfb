"""/metrics, the node_exporter textfile and `trapflow view` against running pipelines."""

from __future__ import annotations

import signal
import socket
import subprocess
from pathlib import Path
from typing import Any

import pytest
from prometheus_client.parser import text_string_to_metric_families

from tests.conftest import Pipeline, poll_for
from tests.integration.viewer_util import attach_viewer, free_port, get, get_json, post, use_token

pytestmark = pytest.mark.slow  # starts whole pipelines


def _samples(text: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for fam in text_string_to_metric_families(text) for s in fam.samples}


def _processed(samples: dict[Any, float], pool: str) -> float:
    return samples[("trapflow_pool_processed_pairs_total", (("pool", pool),))]


@pytest.mark.timeout(150)
def test_metrics_scrape_and_textfile(spawn, run_dir: Path) -> None:
    port = free_port()
    prom = run_dir.parent / "textfile" / "trapflow.prom"
    p: Pipeline = spawn(["--size", "320x240", "--view", str(port), "--metrics-file", str(prom)],
                        run_dir)
    p.wait_active(90)
    use_token(port, run_dir)
    url = f"http://127.0.0.1:{port}/metrics"

    def scrape() -> dict[Any, float] | None:
        code, body = get(url)
        if code != 200:
            return None
        s = _samples(body.decode())
        return s if s.get(("trapflow_pool_processed_pairs_total", (("pool", "mono"),))) else None

    kinds = {"mono": "mono_ir", "stereo": "stereo_ir", "vo": "stereo_vo"}

    def complete(s: dict[Any, float]) -> bool:
        """Every pool has results, latencies and processing times (the last come with the
        workers' heartbeats in the status reply, up to two seconds behind the tap)."""
        return all(
            s.get(("trapflow_result_latency_seconds_count", (("algorithm", kinds[pool]),)), 0)
            > 0 and s.get(("trapflow_pool_processing_seconds_count", (("pool", pool),)), 0) > 0
            for pool in kinds)

    first = poll_for(lambda: (s := scrape()) and complete(s) and s, 40, interval=0.5,
                     what="/metrics with results, latencies and processing times of every pool")
    second = poll_for(lambda: (s := scrape()) and _processed(s, "mono") > _processed(first, "mono")
                      and s, 15, interval=0.5, what="the mono counter to grow")
    # The supervisor reads the same stats from the same tap, a moment later or sooner.
    poll_for(lambda: (st := p.status()) and all(
        _processed(second, pool) <= st["stats"]["pools"][pool]["processed"]
        for pool in kinds), 10, interval=0.3,
        what="the supervisor's counters to reach the scraped ones")
    for pool in kinds:  # counters never go back
        for name in ("trapflow_pool_processed_pairs_total", "trapflow_pool_received_pairs_total",
                     "trapflow_pool_dropped_pairs_total"):
            key = (name, (("pool", pool),))
            assert second[key] >= first[key], key
    assert second[("trapflow_node_state", (("node", "viewer"), ("state", "active")))] == 1
    assert second[("trapflow_pipeline_up", ())] == 1
    # CPU and memory by role (issue 22, item 12): every role of this run, the supervisor too.
    for role in ("supervisor", "broker", "capture", "normalizer", "viewer", *kinds):
        assert second[("trapflow_process_resident_memory_bytes", (("role", role),))] > 1 << 20
        assert second[("trapflow_process_cpu_seconds_total", (("role", role),))] >= \
            first.get(("trapflow_process_cpu_seconds_total", (("role", role),)), 0.0)
    assert second[("trapflow_process_count", (("role", "mono"),))] == 1
    assert second[("trapflow_process_cpu_seconds_total", (("role", "vo"),))] > 0
    # The textfile: there, parseable, the same families, and rewritten on its interval.
    # Processing times come with the workers' heartbeats, up to two seconds after the first
    # counters: a textfile written in between lacks them (it failed one CI run in a few).
    first_text = poll_for(
        lambda: prom.exists() and 'processed_pairs_total{pool="mono"}' in (t := prom.read_text())
        and all(f'processing_seconds_count{{pool="{pool}"}}' in t for pool in kinds) and t,
        20, what=f"{prom.name} written with pool counters and processing times")
    assert {k[0] for k in _samples(first_text)} == {k[0] for k in second}
    poll_for(lambda: prom.read_text() != first_text, 15, what="the textfile rewritten")
    # A cross-site form post cannot stop the trap: the control header is required.
    assert post(f"http://127.0.0.1:{port}/api/stop") == 403
    # Nor a page whose own name was rebound to 127.0.0.1 (DNS rebinding): Host must be local.
    assert post(f"http://127.0.0.1:{port}/api/stop", {"X-Trapflow-Control": "stop",
                                                      "Host": f"evil.example:{port}"}) == 403
    assert p.proc.poll() is None
    code, _, err = p.stop()
    assert code == 0, err


def signal_masks(pid: int) -> str:
    """The signal masks of a process (hexadecimal, bit n-1 for signal n; SIGINT is 0x2)."""
    try:
        lines = Path(f"/proc/{pid}/status").read_text().splitlines()
    except OSError as exc:
        return f"no status: {exc}"
    return ", ".join(ln for ln in lines if ln.startswith(("SigBlk", "SigIgn", "SigCgt")))


@pytest.mark.timeout(150)
def test_view_attaches_to_a_running_pipeline(spawn, run_dir: Path, started_procs) -> None:
    p: Pipeline = spawn(["--size", "320x240"], run_dir)
    p.wait_active(90)
    view, port = attach_viewer(run_dir, started_procs)
    state = poll_for(lambda: (s := get_json(f"http://127.0.0.1:{port}/api/state"))
                     and s["frame"] and s["nodes"] and s["pools"].get("vo", {}).get("rate")
                     and s, 40, interval=0.5, what="a pair, nodes and charts from the taps")
    assert state["frame"]["width"] == 320
    code, jpeg = get(f"http://127.0.0.1:{port}/frame/{state['frame']['seq']}/left.jpg")
    assert code == 200 and jpeg[:2] == b"\xff\xd8"
    assert {n["name"] for n in state["nodes"]} >= {"broker", "capture", "normalizer"}
    # The viewer subscribes each tap only to its own topics: no tap counts it as refused.
    status = p.status()
    assert status is not None
    for n in status["nodes"]:
        if n["name"] in ("broker", "normalizer"):
            assert n["counters"].get("refused_subscriptions", 0) == 0, n
    view.send_signal(signal.SIGINT)
    try:  # its output read while it leaves: a full pipe must not hold it
        _out, err = view.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        masks = signal_masks(view.pid)  # a blocked or ignored SIGINT is inherited
        view.send_signal(signal.SIGABRT)  # its threads' stacks to stderr (faulthandler)
        try:
            _out, err = view.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            view.kill()
            _out, err = view.communicate(timeout=10)
        raise AssertionError(f"trapflow view did not leave within 30 s of Ctrl-C ({masks}); "
                             f"its stderr ended: {err.decode(errors='replace')[-6000:]}"
                             ) from None
    assert view.returncode == 0, err.decode(errors="replace")[-3000:]
    assert p.status() is not None, "detaching the viewer disturbed the pipeline"
    code, _, err = p.stop()
    assert code == 0, err


@pytest.mark.timeout(120)
def test_taken_port_is_a_clear_startup_failure(spawn, run_dir: Path) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        p: Pipeline = spawn(["--size", "320x240", "--view", str(port)], run_dir)
        code, _, err = p.wait(90)
    assert code != 0
    assert f"viewer cannot start: cannot serve on 127.0.0.1:{port}" in err, err
    assert "--view" in err
