"""Prometheus metrics of a pipeline, read from the viewer's state at scrape time.

One collector turns ViewState (broker stats, status reply, result latencies) into metric
families; /metrics serves them and write_textfile() leaves them for node_exporter's
textfile collector. Names follow Prometheus conventions: `trapflow_` prefix, base units
in the name, `_total` on counters; rates are left to PromQL's rate() over counters (a rate
computed here would depend on when and how often it is scraped).
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import psutil
from prometheus_client import CollectorRegistry, generate_latest, write_to_textfile
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    Metric,
    SummaryMetricFamily,
)
from prometheus_client.registry import Collector

from trapflow.runtime.node import ACTIVE, FINALIZED, INACTIVE, UNCONFIGURED
from trapflow.viewer import proc_metrics
from trapflow.viewer.state import ViewState
from trapflow.wire.pool_counters import POOL_COUNTERS, PoolCounter

LIFECYCLE = (UNCONFIGURED, INACTIVE, ACTIVE, FINALIZED)
# The per-pool counts (Prometheus counters) and the numbers of now (gauges); rates are
# left to PromQL's rate() over the counters.
POOL_COUNTS = tuple(c for c in POOL_COUNTERS if c.summed)
POOL_GAUGES = tuple(c for c in POOL_COUNTERS if c.kind in ("procs", "held"))
BUSY_CPU_TIMES = ("user", "nice", "system", "irq", "softirq", "steal")


def _words(c: PoolCounter) -> str:
    return (c.metric or c.name).replace("_", " ")


def _temperature_c() -> float | None:
    try:
        sensors = psutil.sensors_temperatures()
    except (AttributeError, OSError):
        return None
    for entries in sensors.values():
        if entries:
            return float(entries[0].current)
    return None


class PipelineCollector(Collector):
    """Metric families of one pipeline, computed from a ViewState when scraped."""

    def __init__(self, state: ViewState, run_dir: Path) -> None:
        self.state = state
        self.run_dir = run_dir

    def collect(self) -> Iterator[Metric]:
        yield from self._pools()
        yield from self._latency()
        yield from self._nodes()
        yield from self._health()
        yield from proc_metrics.families(self.state.status or {})
        yield from self._energy()

    def _pools(self) -> Iterator[Metric]:
        s = self.state.stats
        pairs = CounterMetricFamily("trapflow_pairs_received", "Pairs the broker received.")
        malformed = CounterMetricFamily("trapflow_malformed_messages",
                                        "Messages the broker could not decode.")
        if s is not None:
            pairs.add_metric([], s.pairs_in)
            malformed.add_metric([], s.malformed)
        yield from (pairs, malformed)
        counters = {c.name: CounterMetricFamily(c.metric_name, f"Pairs {_words(c)} per pool.",
                                                labels=["pool"]) for c in POOL_COUNTS}
        gauges = {c.name: GaugeMetricFamily(c.metric_name, f"{_words(c)} per pool.",
                                            labels=["pool"]) for c in POOL_GAUGES}
        for name, p in (s.pools.items() if s is not None else ()):
            for k, fam in counters.items():
                fam.add_metric([name], getattr(p, k))
            for k, gfam in gauges.items():
                gfam.add_metric([name], getattr(p, k))
        yield from counters.values()
        yield from gauges.values()
        level = GaugeMetricFamily("trapflow_ladder_level", "The degradation ladder's level "
                                  "(1 for the level it is at).", labels=["level"])
        if s is not None and s.level:
            level.add_metric([s.level], 1)
        yield level

    def _latency(self) -> Iterator[Metric]:
        lat = HistogramMetricFamily(
            "trapflow_result_latency_seconds",
            "Capture to result on the normalizer's tap (wall clock), per algorithm.",
            labels=["algorithm"])
        for kind, h in sorted(self.state.latency.items()):
            lat.add_metric([kind], h.cumulative(), sum_value=h.total)
        yield lat
        results = CounterMetricFamily("trapflow_results", "Result lines seen on the tap.",
                                      labels=["algorithm"])
        for kind, count in sorted(self.state.results_in.items()):
            results.add_metric([kind], count)
        yield results
        # Summed over the live workers of each pool (their heartbeat counters): a summary
        # without quantiles; a worker restart resets its part, as Prometheus counters do.
        proc = SummaryMetricFamily("trapflow_pool_processing_seconds",
                                   "Time the plugin spent per processed pair.", labels=["pool"])
        per_pool: dict[str, list[int]] = {}
        for n in self._status_nodes():
            parts = n["name"].split(":")
            if parts[0] == "worker" and len(parts) == 3 and "proc_us" in n.get("counters", {}):
                acc = per_pool.setdefault(parts[1], [0, 0])
                acc[0] += n["counters"].get("processed", 0)
                acc[1] += n["counters"]["proc_us"]
        for pool, (count, us) in sorted(per_pool.items()):
            proc.add_metric([pool], count_value=count, sum_value=us / 1e6)
        yield proc

    def _status_nodes(self) -> list[dict[str, Any]]:
        return list((self.state.status or {}).get("nodes", []))

    def _nodes(self) -> Iterator[Metric]:
        st = self.state.status or {}
        state = GaugeMetricFamily("trapflow_node_state",
                                  "1 for the lifecycle state each node is in, else 0.",
                                  labels=["node", "state"])
        restarts = CounterMetricFamily("trapflow_node_restarts", "Restarts of each node.",
                                       labels=["node"])
        for n in st.get("nodes", []):
            for s in LIFECYCLE:
                state.add_metric([n["name"], s], 1.0 if n["state"] == s else 0.0)
            restarts.add_metric([n["name"]], n["restarts"])
        yield from (state, restarts)
        ring = GaugeMetricFamily("trapflow_ring_slots", "Shared-memory ring slots by state.",
                                 labels=["state"])
        for k, v in (st.get("ring") or {}).items():
            if isinstance(v, int) and k != "slots":
                ring.add_metric([k], v)
        yield ring
        up = GaugeMetricFamily("trapflow_pipeline_up",
                               "1 while the supervisor answers status requests.")
        up.add_metric([], 0.0 if self.state.status_error or not st else 1.0)
        yield up
        uptime = GaugeMetricFamily("trapflow_uptime_seconds", "Seconds since the broker started.")
        uptime.add_metric([], self.state.stats.uptime_s if self.state.stats else 0.0)
        yield uptime

    def _health(self) -> Iterator[Metric]:
        cpu = CounterMetricFamily("trapflow_host_cpu_busy_seconds",
                                  "Host CPU time not idle, all cores (rate() / cores: busy).")
        times = psutil.cpu_times()._asdict()  # guest time is inside user time on Linux
        cpu.add_metric([], sum(times.get(k, 0.0) for k in BUSY_CPU_TIMES))
        yield cpu
        temp = _temperature_c()
        if temp is not None:
            t = GaugeMetricFamily("trapflow_host_temperature_celsius", "First thermal sensor.")
            t.add_metric([], temp)
            yield t
        disk = GaugeMetricFamily("trapflow_run_dir_free_bytes",
                                 "Free bytes on the run directory's file system.")
        if self.run_dir.exists():
            disk.add_metric([], float(shutil.disk_usage(self.run_dir).free))
        yield disk
        modem = next((n for n in (self.state.status or {}).get("nodes", [])
                      if n["name"] == "modem"), None)
        backlog = GaugeMetricFamily("trapflow_outbox_backlog_messages",
                                    "Records waiting in the modem outbox.")
        if modem is not None:
            backlog.add_metric([], modem["counters"].get("backlog", 0))
        yield backlog


    def _energy(self) -> Iterator[Metric]:
        """The run's energy estimate so far (ledger.json's `energy`, from the status reply):
        gauges, as a restarted broker's gate times start again from zero."""
        energy = ((self.state.status or {}).get("ledger") or {}).get("energy") or {}
        single = [("watts", "trapflow_energy_watts", "Estimated power draw (board model)."),
                  ("wh_per_day", "trapflow_energy_watt_hours_per_day",
                   "Estimated energy per day at this run's load."),
                  ("busy_cores", "trapflow_energy_busy_cores", "Mean CPU cores busy."),
                  ("days_on_battery", "trapflow_energy_battery_days",
                   "Days the configured battery lasts at this load."),
                  ("active_s", "trapflow_gate_active_seconds",
                   "Seconds the motion gate was open (motion, hold, tracks, moving rig)."),
                  ("idle_s", "trapflow_gate_idle_seconds",
                   "Seconds the motion gate withheld pairs (or fed only the keep-alive).")]
        for key, name, text in single:
            fam = GaugeMetricFamily(name, text)
            if key in energy:
                fam.add_metric([], float(energy[key]))
            yield fam
        per_role = GaugeMetricFamily("trapflow_energy_cpu_seconds_per_hour",
                                     "CPU seconds per hour of wall time, per role.",
                                     labels=["role"])
        for role, v in sorted((energy.get("cpu_s_per_hour") or {}).items()):
            per_role.add_metric([role], float(v))
        yield per_role


def registry_for(state: ViewState, run_dir: Path) -> CollectorRegistry:
    """A registry of its own (no process metrics of the viewer mixed in)."""
    reg = CollectorRegistry(auto_describe=False)
    reg.register(PipelineCollector(state, run_dir))
    return reg


def exposition(reg: CollectorRegistry) -> bytes:
    """The text exposition format, as /metrics serves it."""
    return generate_latest(reg)


def write_textfile(reg: CollectorRegistry, path: Path) -> None:
    """Write for node_exporter's textfile collector: a temporary file renamed in place."""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_to_textfile(str(path), reg)
