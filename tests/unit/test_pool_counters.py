"""The per-pool counter list is the one home of PoolStats's counters: every view derives
from it, so it must name each counter of the message once, and the broker must keep each
count it sums.

Regression: the list was spelled in six places (broker, ledger, status table, status line,
metrics) and renamed on the way; a counter added to one was missed by another."""

from __future__ import annotations

import dataclasses

import pytest

from trapflow.broker.state import _Pool
from trapflow.wire.messages import PoolStats
from trapflow.wire.pool_counters import DROPS, POOL_COUNTERS, SETTLED, SUMMED, settled

# PoolStats fields that are not counters of pairs or processes.
NOT_COUNTERS = {"failures", "active", "min_interval_s", "latency_ms"}


def test_every_counter_of_pool_stats_is_listed_once() -> None:
    names = [c.name for c in POOL_COUNTERS]
    assert len(names) == len(set(names))
    assert set(names) == set(PoolStats.__struct_fields__) - NOT_COUNTERS


def test_the_broker_keeps_every_count_it_sums() -> None:
    fields = {f.name for f in dataclasses.fields(_Pool)}
    assert set(SUMMED) <= fields


def test_ledger_keys_are_distinct_and_cover_every_final_state() -> None:
    keys = [c.ledger for c in POOL_COUNTERS if c.ledger]
    assert len(keys) == len(set(keys))
    # every state a pair ends in, and the boxes cut from results (a count of boxes)
    assert {c.name for c in POOL_COUNTERS if c.ledger} == {*SETTLED, "lost", "cut"}


@pytest.mark.parametrize(("name", "unit", "metric"), [
    ("workers", "procs", "trapflow_pool_workers"),  # a gauge of processes
    ("received", "pairs", "trapflow_pool_received_pairs"),  # a count since the start
    ("errors", "pairs", "trapflow_pool_failed_pairs"),  # renamed for the metric
    ("pending", "pairs", "trapflow_pool_pending_pairs"),  # a gauge of pairs held now
    ("rate", "pairs/s", "trapflow_pool_rate_pairs_per_second"),  # its unit in the name
    ("cut", "boxes", "trapflow_pool_cut_boxes"),  # boxes, not pairs
])
def test_units_and_metric_names(name: str, unit: str, metric: str) -> None:
    c = next(c for c in POOL_COUNTERS if c.name == name)
    assert (c.unit, c.metric_name) == (unit, metric)


def test_settled_counts_each_final_state_once_and_takes_processed_from_elsewhere() -> None:
    p = PoolStats(received=100, dispatched=90, processed=50, dropped=5, inactive=1,
                  throttled=2, stale=3, gated=4, errors=6, timed_out=7, lost=8, pending=9,
                  in_flight=10, kept=11)
    assert settled(p) == 50 + 5 + 1 + 2 + 3 + 4 + 6 + 7
    assert settled(p, processed=40) == 40 + 5 + 1 + 2 + 3 + 4 + 6 + 7
    assert set(DROPS) == {"dropped", "inactive", "throttled", "stale"}
