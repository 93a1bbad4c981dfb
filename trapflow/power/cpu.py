"""CPU seconds per role over a run (each pool's workers, broker, capture, normalizer, ...,
the supervisor itself), sampled from the children's process times once a second; a
restarted child's time is kept. What the energy estimate of ledger.json is made from."""

from __future__ import annotations

from collections.abc import Iterable

import psutil


def _cpu_s(proc: psutil.Process) -> float:
    t = proc.cpu_times()
    return float(t.user + t.system)


class CpuMeter:
    """Sums CPU time per role; a process that ended keeps its last sample (at most one
    sampling interval of its time is missed)."""

    def __init__(self) -> None:
        self._ended: dict[str, float] = {}
        self._live: dict[int, tuple[str, float]] = {}  # pid -> (role, last sample)
        self._self = psutil.Process()

    def sample(self, children: Iterable[tuple[str, int | None]]) -> None:
        """The live children as (role, pid); pids no longer listed have ended."""
        seen: set[int] = set()
        for role, pid in children:
            if pid is None:
                continue
            try:
                self._live[pid] = (role, _cpu_s(psutil.Process(pid)))
                seen.add(pid)
            except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
                pass  # exited since: its last sample stands
        for pid in [p for p in self._live if p not in seen]:
            role, last = self._live.pop(pid)
            self._ended[role] = self._ended.get(role, 0.0) + last

    def totals(self) -> dict[str, float]:
        """CPU seconds per role so far, the supervisor's own under `supervisor`."""
        out = dict(self._ended)
        for role, last in self._live.values():
            out[role] = out.get(role, 0.0) + last
        out["supervisor"] = out.get("supervisor", 0.0) + _cpu_s(self._self)
        return {k: round(v, 3) for k, v in sorted(out.items())}
