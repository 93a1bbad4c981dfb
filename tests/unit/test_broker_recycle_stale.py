"""The broker core's side of keeping workers healthy (issue 14 part 6), without sockets:
pending pairs older than a pool's max_pending_age_s are dropped as stale on a tick, and a
recycled worker's goodbye queues what it never started again instead of losing it."""

from __future__ import annotations

import pytest

from trapflow.broker.policy import Pending
from trapflow.broker.state import BrokerState, Dispatch, Evicted, PoolSpec, Release
from trapflow.config.schema import parse_policy

W1, W2 = b"w1", b"w2"


def state(policy: str, max_age: float = 0.0, **more: str) -> BrokerState:
    pools = {"p": PoolSpec(parse_policy(policy), 10.0, max_age)}
    pools.update({n: PoolSpec(parse_policy(pol), 10.0) for n, pol in more.items()})
    return BrokerState(pools, idle_liveness_s=100.0)


def seqs(actions: list[object], kind: type) -> list[int]:
    return [a.seq for a in actions if isinstance(a, kind)]  # type: ignore[attr-defined]


# (policy, max_age, arrivals (seq, t), tick at, stale seqs, still pending)
STALE = [
    ("fifo:8", 2.0, [(0, 0.0), (1, 1.0), (2, 2.5)], 3.1, [0, 1], 1),
    ("fifo:8", 2.0, [(0, 0.0), (1, 1.0), (2, 2.5)], 2.0, [], 3),  # exactly 2 s: not older
    ("fifo:8", 2.0, [(0, 0.0), (1, 1.0), (2, 2.5)], 9.0, [0, 1, 2], 0),
    ("fifo:8", 0.0, [(0, 0.0), (1, 1.0)], 1000.0, [], 2),  # 0: no limit
    ("latest", 0.5, [(0, 0.0), (1, 0.2)], 0.6, [], 1),  # latest kept only 1 (0 by policy)
    ("latest", 0.5, [(0, 0.0), (1, 0.2)], 0.8, [1], 0),
    ("ordered:2", 1.0, [(0, 0.0), (1, 0.5), (2, 0.9)], 1.2, [0], 1),  # 2 dropped by policy
]


@pytest.mark.parametrize(("policy", "max_age", "arrivals", "at", "stale", "left"), STALE)
def test_pending_pairs_older_than_max_age_are_dropped_as_stale(
        policy: str, max_age: float, arrivals: list[tuple[int, float]], at: float,
        stale: list[int], left: int) -> None:
    s = state(policy, max_age)
    for seq, t in arrivals:
        s.pair_arrived(seq, t)
    st0 = s.pool_stats()["p"]
    acts = s.tick(at)
    st = s.pool_stats()["p"]
    assert seqs(acts, Release) == stale  # no other pool holds them: their buffers go
    assert (st.stale, st.pending, st.dropped) == (len(stale), left, st0.dropped)
    assert st.received == st.stale + st.pending + st.dropped  # one counter each


def test_a_stale_pair_still_held_by_another_pool_is_not_released() -> None:
    s = state("fifo:4", 1.0, q="fifo:4")
    s.pair_arrived(0, 0.0)
    acts = s.tick(2.0)
    assert seqs(acts, Release) == []  # pool q still holds it
    assert s.pool_stats()["p"].stale == 1 and s.pool_stats()["q"].stale == 0
    assert s.held() == 1


def test_a_dispatched_pair_is_never_stale() -> None:
    s = state("fifo:4", 1.0)
    s.worker_ready(W1, "p", 1, 0.0)
    s.pair_arrived(0, 0.0)  # dispatched at once
    s.tick(5.0)
    st = s.pool_stats()["p"]
    assert (st.stale, st.in_flight) == (0, 1)


def test_policy_change_keeps_arrival_times() -> None:
    s = state("fifo:4", 1.0)
    s.pair_arrived(0, 0.0)
    s.set_policy("p", "fifo:8", 0.9)
    assert seqs(s.tick(1.5), Release) == [0]  # aged from its arrival, not the change


# (policy, what W1 held when it left (seq), pending before, dispatched next to W2, dropped)
REQUEUE = [
    ("fifo:8", [1], [2, 3], [1, 2, 3], []),  # back at the front, in order
    ("ordered:2", [1], [2, 3], [1, 2], [3]),  # full: the newest goes, as ordered drops
    ("latest", [1], [2], [2], [1]),  # latest keeps only the newest
    ("fifo:2", [1], [2, 3], [2, 3], [1]),  # full: the oldest goes, as fifo drops
    ("fifo:8", [], [2], [2], []),  # it held nothing
]


@pytest.mark.parametrize(("policy", "held", "pending", "next_", "dropped"), REQUEUE)
def test_recycled_worker_goodbye_requeues_what_it_never_started(
        policy: str, held: list[int], pending: list[int], next_: list[int],
        dropped: list[int]) -> None:
    """A recycled worker answered its last pair (0), then left: pairs dispatched to it
    after that answer are not lost; the goodbye pair is processed, once."""
    s = state(policy)
    s.worker_ready(W1, "p", 1, 0.0)
    s.pair_arrived(0, 0.0)  # -> W1
    for seq in held:
        s.job_done(W1, "p", 0, True, 0.1)  # its last answer: a credit back, and 1 goes to it
        s.pair_arrived(seq, 0.1)
    if not held:
        s.job_done(W1, "p", 0, True, 0.1)
    for seq in pending:
        s.pair_arrived(seq, 0.2)
    acts = s.worker_gone(W1, "recycled:rss", 0.3, requeue=True)
    ev = [a for a in acts if isinstance(a, Evicted)]
    assert ev and ev[0].lost == ()
    assert sorted(seqs(acts, Release)) == sorted(dropped)
    got = [a.seq for a in s.worker_ready(W2, "p", 8, 0.4) if isinstance(a, Dispatch)]
    assert got == next_
    st = s.pool_stats()["p"]
    assert (st.processed, st.lost, st.dropped) == (1, 0, len(dropped))
    assert W1 not in s.worker_pools()  # nothing more is dispatched to it


def test_gone_without_requeue_still_loses_what_the_worker_held() -> None:
    s = state("fifo:8")
    s.worker_ready(W1, "p", 1, 0.0)
    s.pair_arrived(0, 0.0)
    acts = s.worker_gone(W1, "process exited with status 1", 0.3)
    assert [a.lost for a in acts if isinstance(a, Evicted)] == [(0,)]
    assert s.pool_stats()["p"].lost == 1


def test_requeue_into_a_deactivated_pool_counts_inactive() -> None:
    s = state("fifo:8")
    s.worker_ready(W1, "p", 1, 0.0)
    s.pair_arrived(0, 0.0)
    s.set_active("p", False, 0.1)
    acts = s.worker_gone(W1, "recycled:jobs", 0.2, requeue=True)
    st = s.pool_stats()["p"]
    assert (st.inactive, st.lost, st.pending) == (1, 0, 0) and seqs(acts, Release) == [0]


def test_second_goodbye_changes_nothing() -> None:
    """The worker's own goodbye and the supervisor's (on its exit) both arrive."""
    s = state("fifo:8")
    s.worker_ready(W1, "p", 1, 0.0)
    s.worker_gone(W1, "recycled:rss", 0.1, requeue=True)
    assert s.worker_gone(W1, "recycled:rss", 0.2, requeue=True) == []


@pytest.mark.parametrize(("policy", "pushes", "requeued", "order", "dropped"), [
    ("fifo:4", [5, 6], [(1, 0.0), (2, 0.0)], [1, 2, 5, 6], []),
    ("fifo:3", [5, 6], [(1, 0.0), (2, 0.0)], [2, 5, 6], [1]),
    ("ordered:3", [5, 6], [(2, 0.0), (1, 0.0)], [1, 2, 5], [6]),
    ("latest", [5], [(1, 0.0)], [5], [1]),
])
def test_pending_requeue_keeps_the_policys_bound(
        policy: str, pushes: list[int], requeued: list[tuple[int, float]], order: list[int],
        dropped: list[int]) -> None:
    q = Pending(parse_policy(policy))
    for seq in pushes:
        q.push(seq, 1.0)
    assert q.requeue(requeued) == dropped
    assert [q.pop() for _ in range(len(q))] == order
