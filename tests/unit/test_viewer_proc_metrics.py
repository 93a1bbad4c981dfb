"""/metrics' CPU and memory per role (process-exporter style) and counters in place of the
rates computed at scrape time, read back with prometheus_client's own parser."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest
from prometheus_client.parser import text_string_to_metric_families

from trapflow.viewer import metrics, proc_metrics
from trapflow.viewer.state import ViewState
from trapflow.wire import messages

STATUS: dict[str, Any] = {
    "supervisor_pid": 100,
    "nodes": [
        {"name": "broker", "pid": 101, "state": "active", "restarts": 0, "reason": ""},
        {"name": "worker:mono:0", "pid": 102, "state": "active", "restarts": 1, "reason": ""},
        {"name": "worker:mono:1", "pid": 103, "state": "active", "restarts": 0, "reason": ""},
        {"name": "worker:vo:0", "pid": 104, "state": "active", "restarts": 0, "reason": ""},
        {"name": "capture", "pid": None, "state": "unconfigured", "restarts": 0, "reason": ""},
    ],
    "ledger": {"energy": {"cpu_s": {"broker": 1.5, "mono": 7.25, "vo": 3.0, "capture": 0.5,
                                    "supervisor": 0.75}}},
}
RSS = {100: 50, 101: 60, 102: 200, 103: 210, 104: 120}  # 104 gone below: None


@pytest.mark.parametrize(("node", "role"), [
    ("worker:mono:0", "mono"),   # a worker by its pool, as the CPU meter names it
    ("worker:my_net:12", "my_net"),
    ("broker", "broker"),
    ("viewer", "viewer"),
])
def test_role_of(node: str, role: str) -> None:
    assert proc_metrics.role_of(node) == role


def test_by_role_sums_live_processes_and_keeps_the_meters_cpu() -> None:
    cpu, rss, count = proc_metrics.by_role(STATUS, lambda pid: None if pid == 104 else RSS[pid])
    assert cpu == STATUS["ledger"]["energy"]["cpu_s"]  # restarted processes' time kept
    assert rss == {"supervisor": 50, "broker": 60, "mono": 410}  # vo's process is gone
    assert count == {"supervisor": 1, "broker": 1, "mono": 2}


def _families(st: ViewState, tmp_path: Path) -> dict[str, Any]:
    text = metrics.exposition(metrics.registry_for(st, tmp_path)).decode()
    return {f.name: f for f in text_string_to_metric_families(text)}


def test_exposition_has_cpu_and_memory_by_role_and_no_precomputed_rates(tmp_path: Path) -> None:
    """Regression (issue 22, item 12): /metrics had no per-process CPU or memory, and
    exported rates as gauges computed over the broker's last interval."""
    st = ViewState()
    st.on_stats(messages.Stats(t_wall_ns=0, uptime_s=3.0, pairs_in=30, rate_in=10.0,
                               malformed=0, pools={"mono": messages.PoolStats(
                                   workers=1, received=30, processed=25, rate=8.0)}), now=1.0)
    me = os.getpid()  # a real process to measure: this one, as the "broker"
    st.on_status({**STATUS, "supervisor_pid": None,
                  "nodes": [{**STATUS["nodes"][0], "pid": me}]})
    fams = _families(st, tmp_path)
    cpu = fams["trapflow_process_cpu_seconds"]
    assert cpu.type == "counter"
    assert {s.labels["role"]: s.value for s in cpu.samples if s.name.endswith("_total")} \
        == STATUS["ledger"]["energy"]["cpu_s"]
    rss = fams["trapflow_process_resident_memory_bytes"]
    assert rss.type == "gauge"
    (sample,) = rss.samples
    assert sample.labels == {"role": "broker"} and sample.value > 10 << 20  # Python + numpy
    assert fams["trapflow_process_count"].samples[0].value == 1
    # Rates: counters only (rate() in PromQL); the gauges computed here are gone.
    for gone in ("trapflow_capture_rate_pairs_per_second", "trapflow_pool_rate_pairs_per_second",
                 "trapflow_host_cpu_usage_ratio"):
        assert gone not in fams, gone
    assert fams["trapflow_pairs_received"].type == "counter"
    assert fams["trapflow_pool_processed_pairs"].type == "counter"
    busy = fams["trapflow_host_cpu_busy_seconds"]
    assert busy.type == "counter" and busy.samples[0].value > 0
