"""A run's totals across broker restarts: each broker counts only what it saw.

When a broker dies, its last published counters are kept; what it still held
(pending or in flight) can never finish, so it counts as lost. verdict() reads the
totals at the end: whether the run failed (exit status 1) and the line that says why.
"""

from __future__ import annotations

import msgspec

from trapflow.messages import PoolStats, Stats

FAILED_PREFIX = "failed_"  # capture counters failed_<kind>: pairs skipped at capture
_SUMMED = ("received", "dispatched", "dropped", "processed", "errors", "timed_out", "lost")


def retire(last: Stats) -> Stats:
    """The final counters of a broker that died: what it held is lost."""
    pools = {name: msgspec.structs.replace(
        p, lost=p.lost + p.pending + p.in_flight, pending=0, in_flight=0, workers=0, rate=0.0)
        for name, p in last.pools.items()}
    return msgspec.structs.replace(last, pools=pools, rate_in=0.0)


def combine(base: Stats | None, cur: Stats) -> Stats:
    """Counters of retired brokers (base) added to the live broker's (cur)."""
    if base is None:
        return cur
    pools: dict[str, PoolStats] = {}
    for name in {*base.pools, *cur.pools}:
        a, b = base.pools.get(name, PoolStats()), cur.pools.get(name, PoolStats())
        summed = {k: getattr(a, k) + getattr(b, k) for k in _SUMMED}
        failures = dict(a.failures)
        for kind, n in b.failures.items():
            failures[kind] = failures.get(kind, 0) + n
        pools[name] = msgspec.structs.replace(b, failures=failures, **summed)
    return msgspec.structs.replace(cur, pairs_in=base.pairs_in + cur.pairs_in,
                                   malformed=base.malformed + cur.malformed, pools=pools)


def capture_failures(capture: dict[str, int]) -> dict[str, int]:
    """Pairs skipped at capture by kind (unreadable, truncated, size, too_large...)."""
    return {k[len(FAILED_PREFIX):]: n for k, n in sorted(capture.items())
            if k.startswith(FAILED_PREFIX) and n}


def verdict(source: str, capture: dict[str, int], gave_up: str | None, finished: bool,
            stats: Stats | None) -> list[str]:
    """Why a run failed, one phrase per cause; empty when it did not.

    A finite source that could not go on (gave_up: its reason), one that ended having read
    no pair at all, and a pool that failed every pair it was given (and processed none).
    """
    problems = []
    if gave_up is not None:
        problems.append(f"source {source} could not go on: "
                        f"{gave_up.removeprefix('source failed: ')}")
    elif finished and capture.get("produced", 0) == 0 and capture.get("failed", 0) > 0:
        kinds = ", ".join(f"{k} {n}" for k, n in capture_failures(capture).items())
        problems.append(f"source {source}: none of its {capture['failed']} pairs could be "
                        f"read ({kinds}); see trapflow.log")
    for name, p in sorted(stats.pools.items() if stats else ()):
        # Failed, not timed out: a pool that only ran out of time is slow, not broken.
        if p.errors and p.processed == 0:
            kinds = ", ".join(f"{k} {n}" for k, n in p.failures.items())
            problems.append(f"pool {name} failed every pair it was given ({p.errors}"
                            f"{f': {kinds}' if kinds else ''}); see trapflow.log")
    return problems
