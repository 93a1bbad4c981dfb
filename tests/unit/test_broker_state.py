"""The broker's decisions without sockets: policies, credits, gaps, eviction, accounting."""

from __future__ import annotations

import random

import pytest

from trapflow.broker.state import BrokerState, Dispatch, Evicted, PoolSpec, Rejected, Release
from trapflow.config.schema import parse_policy

W1, W2 = b"w1", b"w2"


def state(**pools: str) -> BrokerState:
    return BrokerState({n: PoolSpec(parse_policy(p), timeout_s=10.0) for n, p in pools.items()},
                       idle_liveness_s=5.0)


def dispatched(actions: list[object]) -> list[tuple[bytes, int, int]]:
    return [(a.worker, a.seq, a.gap) for a in actions if isinstance(a, Dispatch)]


def released(actions: list[object]) -> list[int]:
    return [a.seq for a in actions if isinstance(a, Release)]


def test_no_worker_no_dispatch_latest_keeps_newest() -> None:
    s = state(slow="latest")
    for seq in range(5):
        acts = s.pair_arrived(seq, 0.0)
        assert not dispatched(acts)
        if seq:
            assert released(acts) == [seq - 1]  # the older pending pair is dropped
    acts = s.worker_ready(W1, "slow", 1, 0.0)
    assert dispatched(acts) == [(W1, 4, 0)]
    st = s.pool_stats()["slow"]
    assert (st.received, st.dropped, st.dispatched, st.in_flight) == (5, 4, 1, 1)


def test_fifo_drops_oldest_when_full() -> None:
    s = state(p="fifo:3")
    for seq in range(5):
        s.pair_arrived(seq, 0.0)
    acts = s.worker_ready(W1, "p", 3, 0.0)
    assert [d[1] for d in dispatched(acts)] == [2, 3, 4]
    assert s.pool_stats()["p"].dropped == 2


def test_ordered_reports_gaps_and_keeps_order() -> None:
    s = state(vo="ordered:2")
    s.worker_ready(W1, "vo", 1, 0.0)
    assert dispatched(s.pair_arrived(0, 0.0)) == [(W1, 0, 0)]
    for seq in (1, 2, 3):  # worker busy, bound 2: the newest (3) is dropped, 1 and 2 kept
        s.pair_arrived(seq, 0.0)
    assert dispatched(s.job_done(W1, "vo", 0, True, 0.1)) == [(W1, 1, 0)]
    assert dispatched(s.job_done(W1, "vo", 1, True, 0.2)) == [(W1, 2, 0)]
    s.job_done(W1, "vo", 2, True, 0.3)
    assert dispatched(s.pair_arrived(4, 0.4)) == [(W1, 4, 1)]  # one pair (3) missing before 4
    assert s.pool_stats()["vo"].dropped == 1


def test_capture_side_hole_is_a_gap() -> None:
    s = state(vo="ordered")
    s.worker_ready(W1, "vo", 1, 0.0)
    s.pair_arrived(0, 0.0)
    s.job_done(W1, "vo", 0, True, 0.0)
    assert dispatched(s.pair_arrived(5, 0.0)) == [(W1, 5, 4)]


def test_fan_out_releases_after_last_pool() -> None:
    s = state(a="latest", b="latest")
    s.worker_ready(W1, "a", 1, 0.0)
    s.worker_ready(W2, "b", 1, 0.0)
    acts = s.pair_arrived(0, 0.0)
    assert len(dispatched(acts)) == 2 and not released(acts)
    assert not released(s.job_done(W1, "a", 0, True, 0.0))
    assert released(s.job_done(W2, "b", 0, True, 0.0)) == [0]
    assert s.drained()


def test_least_loaded_worker_first() -> None:
    s = state(p="fifo:10")
    s.worker_ready(W1, "p", 2, 0.0)
    s.worker_ready(W2, "p", 2, 0.0)
    acts = [a for seq in range(4) for a in s.pair_arrived(seq, 0.0)]
    workers = [d[0] for d in dispatched(acts)]
    assert workers.count(W1) == 2 and workers.count(W2) == 2


def test_timeout_evicts_and_counts_lost() -> None:
    s = state(p="latest")
    s.worker_ready(W1, "p", 1, 0.0)
    s.pair_arrived(0, 0.0)
    assert not [a for a in s.tick(9.0) if isinstance(a, Evicted)]
    acts = s.tick(10.5)
    ev = [a for a in acts if isinstance(a, Evicted)]
    assert ev and ev[0].lost == (0,) and "timeout" in ev[0].reason
    assert released(acts) == [0]
    st = s.pool_stats()["p"]
    assert (st.timed_out, st.lost, st.workers) == (1, 0, 0)


def test_idle_silent_worker_evicted_then_rejoins_on_heartbeat() -> None:
    s = state(p="latest")
    s.worker_ready(W1, "p", 1, 0.0)
    ev = [a for a in s.tick(6.0) if isinstance(a, Evicted)]
    assert ev and ev[0].lost == ()
    s.pair_arrived(0, 6.0)
    assert dispatched(s.worker_seen(W1, "p", 1, 6.1)) == [(W1, 0, 0)]


def test_done_from_evicted_worker_counts_once_and_rejoins() -> None:
    s = state(p="latest")
    s.worker_ready(W1, "p", 1, 0.0)
    s.pair_arrived(0, 0.0)
    s.tick(11.0)  # evicted: pair 0 lost
    s.pair_arrived(1, 11.0)
    acts = s.job_done(W1, "p", 0, True, 11.5)
    assert dispatched(acts) == [(W1, 1, 0)]
    st = s.pool_stats()["p"]
    assert (st.processed, st.timed_out) == (0, 1)


def test_worker_gone_frees_its_pairs_now() -> None:
    s = state(p="latest")
    s.worker_ready(W1, "p", 1, 0.0)
    s.pair_arrived(0, 0.0)
    acts = s.worker_gone(W1, "exited", 0.5)
    assert released(acts) == [0] and s.pool_stats()["p"].lost == 1


@pytest.mark.parametrize(("pool", "credit"), [("nosuch", 1), ("p", 0), ("p", -3)])
def test_bad_ready_ignored(pool: str, credit: int) -> None:
    s = state(p="latest")
    s.pair_arrived(0, 0.0)
    assert s.worker_ready(W1, pool, credit, 0.0) == []


def test_no_pools_releases_at_once() -> None:
    assert BrokerState({}).pair_arrived(0, 0.0) == [Release(0)]


@pytest.mark.parametrize("seed", range(20))
def test_every_pair_ends_in_exactly_one_counter(seed: int) -> None:
    """Random event sequences: received = processed + errors + dropped + stale + lost +
    pending + in flight, and every seq released exactly once, once no pool holds it (also
    with recycled workers' pairs queued again and stale pairs dropped)."""
    rng = random.Random(seed)
    pools = {"a": "latest", "b": "fifo:3", "c": "ordered:4"}
    s = BrokerState({n: PoolSpec(parse_policy(p), timeout_s=10.0,
                                 max_pending_age_s=1.0 if n == "b" else 0.0)
                     for n, p in pools.items()}, idle_liveness_s=5.0)
    workers = {"a": [b"a1", b"a2"], "b": [b"b1"], "c": [b"c1"]}
    in_flight: dict[bytes, list[int]] = {w: [] for ws in workers.values() for w in ws}
    pool_of = {w: p for p, ws in workers.items() for w in ws}
    released_seqs: list[int] = []
    now, seq = 0.0, 0

    def take(acts: list[object]) -> None:
        for a in acts:
            if isinstance(a, Dispatch):
                in_flight[a.worker].append(a.seq)
            elif isinstance(a, Release):
                released_seqs.append(a.seq)
            elif isinstance(a, Evicted):
                in_flight[a.worker].clear()

    for w, p in pool_of.items():
        take(s.worker_ready(w, p, rng.choice([1, 2]), now))
    for _ in range(400):
        now += rng.uniform(0.0, 0.5)
        r = rng.random()
        if r < 0.45:
            take(s.pair_arrived(seq, now))
            seq += 1
        elif r < 0.9:
            w = rng.choice(list(in_flight))
            if in_flight[w]:
                done = in_flight[w].pop(0)
                ok = rng.random() < 0.9
                take(s.job_done(w, pool_of[w], done, ok, now, rng.choice(["A", "B"])))
        elif r < 0.95:
            take(s.tick(now + rng.choice([0.0, 20.0])))
        else:
            w = rng.choice(list(in_flight))
            take(s.worker_gone(w, "test", now, requeue=rng.random() < 0.5))
            take(s.worker_ready(w, pool_of[w], 1, now))
    for name, st in s.pool_stats().items():
        total = (st.processed + st.errors + st.dropped + st.timed_out + st.lost + st.pending
                 + st.in_flight + st.stale)
        assert st.received == seq, name
        assert total == st.received, (name, st)
        assert sum(st.failures.values()) == st.errors
    assert len(released_seqs) == len(set(released_seqs))
    assert len(released_seqs) + s.held() == seq
    take(s.finish())  # the run ends: nothing pending or in flight remains unaccounted
    for st in s.pool_stats().values():
        assert st.pending == st.in_flight == 0
        assert st.processed + st.errors + st.dropped + st.timed_out + st.lost + st.stale == seq
    assert sorted(released_seqs) == list(range(seq)) and s.drained()


def _answered(s: BrokerState) -> tuple[int, int, int]:
    st = s.pool_stats()["p"]
    return st.processed, st.errors, st.in_flight


@pytest.mark.parametrize(("who", "pool", "seq", "ok", "reason"), [
    (W2, "p", 0, True, "unknown_worker"),  # a Done from a worker that was never given pair 0
    (W2, "p", 0, False, "unknown_worker"),  # the same as a Failed
    (W1, "nosuch", 0, True, "unknown_pool"),  # a pool that does not exist
    (W1, "q", 0, True, "unknown_worker"),  # W1 is in pool p, not q
    (W1, "p", 7, True, "not_dispatched"),  # a pair that never reached W1
    (W1, "p", -1, True, "not_dispatched"),
    (W1, "p", 2**62, True, "not_dispatched"),
])
def test_forged_answers_are_rejected_and_change_nothing(
        who: bytes, pool: str, seq: int, ok: bool, reason: str) -> None:
    """Issue 16 item 2: a Done for a pair never dispatched to that worker was written."""
    s = state(p="latest", q="latest")
    s.worker_ready(W1, "p", 1, 0.0)
    s.worker_ready(W2, "q", 1, 0.0)
    s.pair_arrived(0, 0.0)  # dispatched to W1 in p (and to W2 in q)
    s.pair_arrived(1, 0.0)  # pending in p: W1 has no credit left
    before = (_answered(s), s.held())
    acts = s.job_done(who, pool, seq, ok, 0.5)
    assert [(a.worker, a.pool, a.seq, a.reason) for a in acts if isinstance(a, Rejected)] == [
        (who, pool, seq, reason)]
    assert not dispatched(acts) and not released(acts)  # no credit came back
    assert (_answered(s), s.held()) == before
    assert s.rejected == {reason: 1}


def test_second_answer_for_one_pair_is_rejected() -> None:
    """Issue 16 item 2: a replayed Done (the same worker, the same pair) is taken once."""
    s = state(p="latest")
    s.worker_ready(W1, "p", 1, 0.0)
    s.pair_arrived(0, 0.0)
    assert released(s.job_done(W1, "p", 0, True, 0.1)) == [0]
    acts = s.job_done(W1, "p", 0, True, 0.2)
    assert [a.reason for a in acts if isinstance(a, Rejected)] == ["not_dispatched"]
    assert s.pool_stats()["p"].processed == 1


def test_late_answer_of_gone_worker_is_rejected() -> None:
    """A worker whose process exited cannot answer: its name answering is someone else."""
    s = state(p="latest")
    s.worker_ready(W1, "p", 1, 0.0)
    s.pair_arrived(0, 0.0)
    s.worker_gone(W1, "exited", 0.5)
    acts = s.job_done(W1, "p", 0, True, 0.6)
    assert [a.reason for a in acts if isinstance(a, Rejected)] == ["unknown_worker"]


def test_late_answer_of_timed_out_worker_is_taken_once() -> None:
    s = state(p="latest")
    s.worker_ready(W1, "p", 1, 0.0)
    s.pair_arrived(0, 0.0)
    s.tick(11.0)
    assert not [a for a in s.job_done(W1, "p", 0, True, 11.5) if isinstance(a, Rejected)]
    assert s.late == 1
    again = s.job_done(W1, "p", 0, True, 11.6)
    assert [a.reason for a in again if isinstance(a, Rejected)] == ["not_dispatched"]


@pytest.mark.parametrize(("who", "seq", "named", "reason"), [
    (W1, 0, (0, "p"), None),  # the result of the pair W1 holds, in its pool: taken
    (W1, 0, (123456789, "p"), "result_seq"),  # a result for a pair W1 was never given
    (W1, 0, (1, "p"), "result_seq"),  # for a pair that exists but is pending, not W1's
    (W1, 0, (0, "q"), "result_pool"),  # the right pair, another pool's result (W2's)
    (W1, 0, (7, "q"), "result_seq"),  # both wrong: the seq is named first
    (W1, 0, (-1, ""), "result_seq"),
    (W1, 7, (0, "p"), "not_dispatched"),  # the Done itself is forged: that reason wins
    (W2, 0, (0, "p"), "unknown_worker"),  # W2 is in pool q: its Done for p is refused first
])
def test_result_must_name_the_pair_and_pool_of_its_done(
        who: bytes, seq: int, named: tuple[int, str], reason: str | None) -> None:
    """Issue 26 item 4: a worker attached any result to a pair it was given (pair 179
    answered with a "scallop 0.99" for seq 123456789, written): the broker checked the Done
    but forwarded the result unread. A result must name the Done's seq and pool."""
    s = state(p="latest", q="latest")
    s.worker_ready(W1, "p", 1, 0.0)
    s.worker_ready(W2, "q", 1, 0.0)
    s.pair_arrived(0, 0.0)  # dispatched to W1 in p and to W2 in q
    s.pair_arrived(1, 0.0)  # pending in p
    before = (_answered(s), s.held())
    acts = s.job_done(who, "p", seq, True, 0.5, named=named)
    rejected = [(a.reason, a.named) for a in acts if isinstance(a, Rejected)]
    if reason is None:
        assert not rejected and _answered(s) == (1, 0, 1)  # pair 1 went to W1 at once
        assert s.rejected == {}
        return
    assert rejected == [(reason, named if reason.startswith("result_") else None)]
    assert not dispatched(acts) and not released(acts)  # no credit came back
    assert (_answered(s), s.held()) == before
    assert s.rejected == {reason: 1}


def test_late_answer_with_a_foreign_result_is_rejected_and_the_true_one_still_taken() -> None:
    """Issue 26 item 4: the late path (a timed-out worker answering once) checks the result
    too, and a refused one does not use up the late answer."""
    s = state(p="latest")
    s.worker_ready(W1, "p", 1, 0.0)
    s.pair_arrived(0, 0.0)
    s.tick(11.0)  # W1 timed out holding pair 0
    acts = s.job_done(W1, "p", 0, True, 11.5, named=(5, "p"))
    assert [a.reason for a in acts if isinstance(a, Rejected)] == ["result_seq"]
    assert s.late == 0
    assert not [a for a in s.job_done(W1, "p", 0, True, 11.6, named=(0, "p"))
                if isinstance(a, Rejected)]
    assert s.late == 1


def _room_after(policy: str, pending: int, workers: int = 1, active: bool = True,
                interval_s: float = 0.0) -> bool:
    """has_room() of one pool whose only worker is busy with pair 0 and `pending` more wait."""
    s = state(p=policy, fast="latest")
    s.worker_ready(b"f", "fast", 8, 0.0)  # a pool that always has room
    for i in range(workers):
        s.worker_ready(b"w%d" % i, "p", 1, 0.0)
    for seq in range(workers + pending):  # the first `workers` pairs are taken at once
        s.pair_arrived(seq, 0.0)
    if not active:
        s.set_active("p", False, 0.0)
    if interval_s:
        s.set_interval("p", interval_s, 0.0)
    return s.has_room()


@pytest.mark.parametrize(("policy", "pending", "workers", "active", "interval_s", "room"), [
    ("latest", 0, 1, True, 0.0, True),      # its worker is busy, nothing waits: one more fits
    ("latest", 1, 1, True, 0.0, False),     # one waits: the next would replace (drop) it
    ("fifo:3", 2, 1, True, 0.0, True),
    ("fifo:3", 3, 1, True, 0.0, False),     # full: the next would drop the oldest
    ("ordered:2", 2, 1, True, 0.0, False),  # full: the next would be dropped (a gap for VO)
    ("latest", 1, 0, True, 0.0, True),      # no worker at all: it never holds the source
    ("latest", 1, 1, False, 0.0, True),     # deactivated: its pairs count inactive anyway
    ("latest", 1, 1, True, 5.0, True),      # throttled by the ladder: dropped by design
])
def test_has_room_is_what_back_pressure_waits_for(policy: str, pending: int, workers: int,
                                                  active: bool, interval_s: float,
                                                  room: bool) -> None:
    """Regression (issue 22, item 2): a replay at rate 0 outran its pools, which dropped most
    pairs. Capture now waits while has_room() is false; every row says why it is or not."""
    assert _room_after(policy, pending, workers, active, interval_s) is room


@pytest.mark.parametrize(("paced", "holds"), [
    (True, True),    # a replay at rate 0: capture waits for room
    (False, False),  # any other source: never held back, the policy drops (unchanged)
])
def test_only_a_paced_source_is_held_back(paced: bool, holds: bool) -> None:
    s = BrokerState({"p": PoolSpec(parse_policy("latest"), timeout_s=10.0)}, paced=paced)
    s.worker_ready(W1, "p", 1, 0.0)
    s.pair_arrived(0, 0.0)  # at the worker
    assert not s.holds_source()
    s.pair_arrived(1, 0.0)  # pending: the next would replace it
    assert s.holds_source() is holds
