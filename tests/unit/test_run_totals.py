"""Run totals across broker restarts: counters add up, and a dead broker's holdings are lost."""

from __future__ import annotations

from trapflow.supervisor import ledger as run_totals
from trapflow.wire.messages import PoolStats, Stats


def _stats(uptime: float, **pool: int) -> Stats:
    return Stats(t_wall_ns=0, uptime_s=uptime, pairs_in=pool.get("received", 0), rate_in=1.0,
                 malformed=1, pools={"vo": PoolStats(**pool, failures={"ProtocolError": 1})})


def test_a_dead_broker_keeps_its_counts_and_loses_what_it_held() -> None:
    dead = _stats(9.0, workers=1, received=100, processed=90, dropped=2, pending=3,
                  in_flight=2, lost=1, errors=2)
    base = run_totals.retire(dead)
    assert base.pools["vo"].lost == 1 + 3 + 2
    assert base.pools["vo"].pending == base.pools["vo"].in_flight == 0
    live = _stats(2.0, workers=1, received=30, processed=28, pending=1, in_flight=1)
    total = run_totals.combine(base, live)
    vo = total.pools["vo"]
    assert (vo.received, vo.processed, vo.dropped, vo.lost, vo.errors) == (130, 118, 2, 6, 2)
    assert (vo.pending, vo.in_flight, vo.workers) == (1, 1, 1)  # the live broker's
    assert vo.failures == {"ProtocolError": 2}
    assert total.pairs_in == 130 and total.malformed == 2 and total.uptime_s == 2.0
    # Every pair the two brokers received ends in exactly one state.
    ended = vo.processed + vo.dropped + vo.lost + vo.errors + vo.timed_out
    assert ended + vo.pending + vo.in_flight == vo.received


def test_without_a_retired_broker_the_live_counts_are_the_totals() -> None:
    live = _stats(1.0, received=5, processed=5)
    assert run_totals.combine(None, live) is live
