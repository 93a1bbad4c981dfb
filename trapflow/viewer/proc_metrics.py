"""Per-role CPU and memory of a pipeline's processes for /metrics, as process-exporter gives
them per process group: CPU seconds as a counter (the supervisor's CPU meter, which keeps a
restarted process's time, so the counter never goes back), resident memory and the number
of live processes as gauges, grouped by role (a worker by its pool: `mono`, `vo`...; the
supervisor as `supervisor`). Read from the status reply at scrape time; resident memory
from the processes themselves, by pid, through `rss_of` (psutil in the viewer)."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from typing import Any

import psutil
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric


def role_of(node: str) -> str:
    """The role a node's processes are counted under: `worker:mono:0` -> `mono` (its pool,
    as the CPU meter and ledger.json's energy name it), `broker` -> `broker`."""
    parts = node.split(":")
    return parts[1] if parts[0] == "worker" and len(parts) == 3 else parts[0]


def rss_bytes(pid: int) -> int | None:
    """Resident memory of a live process; None when it is gone or not ours to read."""
    try:
        return int(psutil.Process(pid).memory_info().rss)
    except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
        return None


def by_role(status: Mapping[str, Any], rss_of: Callable[[int], int | None]
            ) -> tuple[dict[str, float], dict[str, int], dict[str, int]]:
    """CPU seconds, resident bytes and live processes per role, from a status reply."""
    energy = (status.get("ledger") or {}).get("energy") or {}
    cpu = {str(k): float(v) for k, v in (energy.get("cpu_s") or {}).items()}
    pids = [(role_of(n["name"]), n.get("pid")) for n in status.get("nodes", [])]
    pids.append(("supervisor", status.get("supervisor_pid")))
    rss: dict[str, int] = {}
    count: dict[str, int] = {}
    for role, pid in pids:
        got = rss_of(pid) if isinstance(pid, int) and pid > 0 else None
        if got is not None:
            rss[role] = rss.get(role, 0) + got
            count[role] = count.get(role, 0) + 1
    return cpu, rss, count


def families(status: Mapping[str, Any], rss_of: Callable[[int], int | None] = rss_bytes
             ) -> Iterator[Metric]:
    """trapflow_process_cpu_seconds_total, _resident_memory_bytes and _count, by role."""
    cpu, rss, count = by_role(status, rss_of)
    seconds = CounterMetricFamily("trapflow_process_cpu_seconds",
                                  "CPU seconds (user and system) of the pipeline's processes by "
                                  "role, restarted processes' time included.", labels=["role"])
    for role, s in sorted(cpu.items()):
        seconds.add_metric([role], s)
    memory = GaugeMetricFamily("trapflow_process_resident_memory_bytes",
                               "Resident memory of the live processes of each role.",
                               labels=["role"])
    live = GaugeMetricFamily("trapflow_process_count", "Live processes of each role.",
                             labels=["role"])
    for role in sorted(rss):
        memory.add_metric([role], rss[role])
        live.add_metric([role], count[role])
    yield from (seconds, memory, live)
