"""The broker's core with gated pools, without sockets: what a gated pool gets on a still
scene and when motion begins, what it holds for pre-roll, and that ungated pools and the
ledger of every pair are as they were."""

from __future__ import annotations

import random

import pytest

from trapflow.broker.state import Action, BrokerState, Dispatch, GateNotice, PoolSpec, Release
from trapflow.config.schema import parse_policy
from trapflow.gate.policy import GateConfig

W_GATED, W_ALL = b"wg", b"wa"
DT = 0.25  # seconds between pairs (exact in binary: the table's times are exact)
RULES = GateConfig(pre_roll=2, keepalive_s=1.0, hold_s=0.5)
F, T = False, True


def gated_state(policy: str, rules: GateConfig = RULES) -> BrokerState:
    """Pool g gated, pool vo (ordered, never gated) taking everything."""
    return BrokerState({"g": PoolSpec(parse_policy(policy), timeout_s=10.0),
                        "vo": PoolSpec(parse_policy("ordered:16"), timeout_s=10.0)},
                       idle_liveness_s=60.0, gates={"g": rules})


def run(s: BrokerState, motions: list[bool | None]) -> tuple[list[int], list[int]]:
    """Pairs 0.. at DT apart with these motion results; workers with room for everything
    answer each pair at once. Returns the seqs the gated pool got, in order, and every
    released seq (the finish included)."""
    s.worker_ready(W_GATED, "g", 64, 0.0)
    s.worker_ready(W_ALL, "vo", 64, 0.0)
    got: list[int] = []
    released: list[int] = []
    for seq, motion in enumerate(motions):
        now = seq * DT
        todo = s.pair_arrived(seq, now, motion, 0.1 if motion else 0.0)
        while todo:
            a = todo.pop(0)
            if isinstance(a, Dispatch):
                got += [a.seq] if a.pool == "g" else []
                todo += s.job_done(a.worker, a.pool, a.seq, True, now)
            elif isinstance(a, Release):
                released.append(a.seq)
    released += [a.seq for a in s.finish() if isinstance(a, Release)]
    return got, released


@pytest.mark.parametrize(("policy", "rules", "motions", "fed", "gated"), [
    # Still scene: only the keep-alive, one pair a second (0, 4, 8, 12); the rest gated.
    ("fifo:8", RULES, [F] * 13, [0, 4, 8, 12], 9),
    # Motion at 6: the pre-roll (the last 2 withheld, 3 and 5) in order before it, the hold
    # (0.5 s: 7 and 8) after it; 1 and 2 were pushed out of the pre-roll, 9 ends kept.
    ("fifo:8", RULES, [F] * 6 + [T] + [F] * 3, [0, 4, 3, 5, 6, 7, 8], 3),
    # A latest pool takes no pre-roll (config gives it 0): withheld pairs are gated at once.
    ("latest", GateConfig(pre_roll=0, keepalive_s=1.0, hold_s=0.5),
     [F] * 6 + [T] + [F] * 3, [0, 4, 6, 7, 8], 5),
    # Every pair moving: every pair fed, none gated.
    ("fifo:8", RULES, [T] * 6, [0, 1, 2, 3, 4, 5], 0),
    # No motion result on the header (a capture without a gate): fail open, feed them all.
    ("fifo:8", RULES, [None] * 5, [0, 1, 2, 3, 4], 0),
])
def test_a_gated_pool_gets_what_the_gate_lets_through(
        policy: str, rules: GateConfig, motions: list[bool | None], fed: list[int],
        gated: int) -> None:
    s = gated_state(policy, rules)
    got, released = run(s, motions)
    assert got == fed
    stats = s.pool_stats()
    g, vo = stats["g"], stats["vo"]
    assert (g.received, g.processed, g.gated, g.dropped, g.lost, g.kept) == (
        len(motions), len(fed), gated, 0, 0, 0)
    assert g.received == g.processed + g.gated  # the ledger adds up, gated counted
    assert (vo.processed, vo.gated) == (len(motions), 0)  # never gated: every pair
    assert sorted(released) == list(range(len(motions))) and s.drained()


def play(s: BrokerState, events: list[tuple[object, ...]]) -> tuple[list[int], list[Action]]:
    """Events at DT apart: ("pair", motion) for the next seq, ("hint", tracks, rig moving)
    as the normalizer says it, ("throttle", interval) as the ladder sets it. Workers answer
    at once. Returns the seqs the gated pool got and every other action of the broker."""
    s.worker_ready(W_GATED, "g", 64, 0.0)
    s.worker_ready(W_ALL, "vo", 64, 0.0)
    got: list[int] = []
    said: list[Action] = []
    seq = 0
    for i, ev in enumerate(events):
        now = i * DT
        if ev[0] == "pair":
            todo = s.pair_arrived(seq, now, bool(ev[1]), 0.1 if ev[1] else 0.0)
            seq += 1
        elif ev[0] == "hint":
            todo = s.gate_hint(int(ev[1]), bool(ev[2]), now)  # type: ignore[call-overload]
        elif ev[0] == "throttle":
            todo = s.set_interval("g", float(ev[1]), now)  # type: ignore[arg-type]
        else:
            raise TypeError(f"unknown event {ev!r}")
        while todo:
            a = todo.pop(0)
            if isinstance(a, Dispatch):
                got += [a.seq] if a.pool == "g" else []
                todo += s.job_done(a.worker, a.pool, a.seq, True, now)
            elif not isinstance(a, Release):
                said.append(a)
    return got, said


def pairs(*motions: bool) -> list[tuple[object, ...]]:
    return [("pair", m) for m in motions]


NOTICE_OFF = GateNotice("motion gate off: the rig moves, every pair is fed")
NOTICE_ON = GateNotice("motion gate on: the rig is still")


@pytest.mark.parametrize(("events", "fed", "notices"), [
    # Tracks alive (the normalizer's word) hold the gate open on a still scene; their end
    # closes it (0..4 held; then withheld until the keep-alive 1 s after 4: 7).
    ([("hint", 1, False)] + pairs(*[F] * 5) + [("hint", 0, False)] + pairs(*[F] * 3),
     [0, 1, 2, 3, 4, 7], []),
    # No tracks: only the keep-alive.
    ([("hint", 0, False)] + pairs(*[F] * 5), [0, 4], []),
    # The rig moves: every pair fed with one notice (said again: still one); still again:
    # the hold (0.5 s) while the background is learnt afresh, then gated.
    (pairs(F, F) + [("hint", 0, True)] + pairs(F, F) + [("hint", 0, True)] + pairs(F)
     + [("hint", 0, False)] + pairs(*[F] * 5), [0, 2, 3, 4, 5, 6], [NOTICE_OFF, NOTICE_ON]),
    # The ladder and the gate agree: a throttled pool (one pair a second) gets no more when
    # motion and its pre-roll come at once; the gate never raises a level's rate.
    ([("throttle", 1.0)] + pairs(F, F, F, T, T, T, T, T), [0, 4], []),
])
def test_the_normalizers_word_and_the_ladder(events: list[tuple[object, ...]], fed: list[int],
                                             notices: list[Action]) -> None:
    s = gated_state("fifo:8")
    got, said = play(s, events)
    assert got == fed
    assert said == notices
    s.finish()
    g = s.pool_stats()["g"]
    n = sum(ev[0] == "pair" for ev in events)
    assert g.received == n == g.processed + g.gated + g.throttled  # the ledger adds up


def test_a_hint_without_a_gated_pool_changes_nothing() -> None:
    s = BrokerState({"a": PoolSpec(parse_policy("fifo:3"), timeout_s=1.0)})
    assert s.gate_hint(3, True, 0.0) == []


def test_a_kept_pair_holds_its_slot_until_fed_or_gated() -> None:
    """Keep: the gated pool's hold stays (the ring slot is not released while the pair may
    still be fed as pre-roll); Gated lets it go."""
    s = gated_state("fifo:8")
    s.worker_ready(W_ALL, "vo", 64, 0.0)
    s.worker_ready(W_GATED, "g", 64, 0.0)
    assert [a.seq for a in s.pair_arrived(0, 0.0, False) if isinstance(a, Dispatch)] == [0, 0]
    acts = s.pair_arrived(1, DT, False)  # kept as pre-roll
    assert [a.pool for a in acts if isinstance(a, Dispatch)] == ["vo"]
    assert not any(isinstance(a, Release) for a in s.job_done(W_ALL, "vo", 1, True, DT))
    assert s.pool_stats()["g"].kept == 1 and s.held() == 2  # 0 in flight, 1 kept
    s.pair_arrived(2, 2 * DT, False)
    acts = s.pair_arrived(3, 3 * DT, False)  # a third withheld pair pushes 1 out: gated
    # vo answered 1 long ago: gated, nobody holds it, its slot goes.
    assert [a.seq for a in acts if isinstance(a, Release)] == [1]
    assert s.pool_stats()["g"].gated == 1
    acts = s.job_done(W_ALL, "vo", 2, True, 3 * DT)
    assert not any(isinstance(a, Release) for a in acts)  # 2 is kept by g


def test_finish_gates_the_kept_pre_roll_instead_of_losing_it() -> None:
    s = gated_state("fifo:8")
    for seq in range(3):
        s.pair_arrived(seq, seq * DT, False)
    acts = s.finish()
    g = s.pool_stats()["g"]
    assert (g.gated, g.kept, g.lost) == (2, 0, 1)  # 1, 2 kept -> gated; 0 pending -> lost
    assert sorted(a.seq for a in acts if isinstance(a, Release)) == [0, 1, 2]
    assert s.drained()


@pytest.mark.parametrize("seed", range(10))
def test_ungated_pools_run_exactly_as_without_a_gate(seed: int) -> None:
    """The same events give an ungated pool the same dispatches and counters whether or not
    a gated pool sits beside it."""
    rng = random.Random(seed)
    specs = {"a": PoolSpec(parse_policy("fifo:3"), timeout_s=1.0)}
    plain = BrokerState(dict(specs), idle_liveness_s=60.0)
    both = BrokerState({**specs, "g": PoolSpec(parse_policy("fifo:8"), timeout_s=1.0)},
                       idle_liveness_s=60.0, gates={"g": RULES})
    logs: list[list[tuple[int, int]]] = [[], []]
    flight: list[list[int]] = [[], []]
    for step in range(200):
        now = step * 0.05
        event = rng.random()
        motion = rng.random() < 0.2
        ok = rng.random() < 0.9
        for i, s in enumerate((plain, both)):
            if event < 0.5:
                acts = s.pair_arrived(step, now, motion, 0.1 if motion else 0.0)
            elif event < 0.7:
                acts = s.worker_ready(b"w", "a", 1, now)
            elif event < 0.9 and flight[i]:
                acts = s.job_done(b"w", "a", flight[i].pop(0), ok, now)
            else:
                acts = s.tick(now)
            for a in acts:
                if isinstance(a, Dispatch) and a.pool == "a":
                    logs[i].append((a.seq, a.gap))
                    flight[i].append(a.seq)
    assert logs[0] == logs[1]
    assert plain.pool_stats()["a"] == both.pool_stats()["a"]


def test_gated_pools_from_config_give_a_latest_pool_no_pre_roll() -> None:
    from trapflow.config.schema import from_data
    from trapflow.gate.policy import gated_pools

    cfg = from_data({"pools": {"mono": {"gate": "motion"},
                               "stereo": {"gate": "motion", "policy": "fifo:6"},
                               # The pre-roll is queued at once with the pair that moved:
                               # a fifo:N pool takes at most N - 1 of it (a config of
                               # before the default gate, fifo:4, stays valid).
                               "small": {"gate": "motion", "policy": "fifo:4"}},
                     "gate": {"pre_roll": 5, "keepalive_s": 2.0, "hold_s": 1.0,
                              "busy_rate_hz": 2.0}})
    assert gated_pools(cfg) == {
        "mono": GateConfig(pre_roll=0, keepalive_s=2.0, hold_s=1.0, busy_rate_hz=2.0),
        "stereo": GateConfig(pre_roll=5, keepalive_s=2.0, hold_s=1.0, busy_rate_hz=2.0),
        "small": GateConfig(pre_roll=3, keepalive_s=2.0, hold_s=1.0, busy_rate_hz=2.0)}
    # The default gates the recognisers (latest pools: no pre-roll), never VO or tags.
    rules = GateConfig(pre_roll=0, keepalive_s=5.0, hold_s=3.0, busy_rate_hz=3.0)
    assert gated_pools(from_data({})) == {"mono": rules, "stereo": rules}


def test_the_busy_rate_paces_by_capture_time_and_the_ledger_counts_the_rest_gated() -> None:
    """Every pair moving, one pair a second allowed while busy: pairs captured 0.25 s apart
    but arriving in one burst (a stalled link catching up) are paced by their capture time,
    so the gated pool gets 0, 4, 8; the rest are counted gated, none dropped or lost."""
    s = gated_state("latest", GateConfig(pre_roll=0, keepalive_s=5.0, hold_s=0.5,
                                         busy_rate_hz=1.0))
    s.worker_ready(W_GATED, "g", 64, 0.0)
    s.worker_ready(W_ALL, "vo", 64, 0.0)
    got: list[int] = []
    for seq in range(11):
        todo = s.pair_arrived(seq, 3.0, True, 0.1, captured=seq * DT)
        while todo:
            a = todo.pop(0)
            if isinstance(a, Dispatch):
                got += [a.seq] if a.pool == "g" else []
                todo += s.job_done(a.worker, a.pool, a.seq, True, 3.0)
    s.finish()
    g = s.pool_stats()["g"]
    assert got == [0, 4, 8]
    assert (g.received, g.processed, g.gated, g.dropped, g.lost) == (11, 3, 8, 0, 0)
