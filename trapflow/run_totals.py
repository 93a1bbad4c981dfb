"""A run's totals across broker restarts: each broker counts only what it saw.

When a broker dies, its last published counters are kept; what it still held
(pending or in flight) can never finish, so it counts as lost.
"""

from __future__ import annotations

import msgspec

from trapflow.messages import PoolStats, Stats

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
