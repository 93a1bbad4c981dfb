"""The gate's decision core: which pairs a gated pool gets, which are gated, and when."""

from __future__ import annotations

from collections.abc import Iterable

import pytest

from trapflow.gate.policy import (
    Action,
    Feed,
    GateConfig,
    Gated,
    GateState,
    Keep,
    Notice,
)

HZ = 10.0
# An event: ("pair", seq, moved) at seq / HZ (captured then too), ("cap", seq, moved,
# captured) at seq / HZ captured at `captured` s, ("alive" | "ended", track, t), ("tracks",
# count, t) as the normalizer says it, ("rig", moving, t), ("tick", t).
Event = tuple[object, ...]


def still(first: int, last: int) -> list[Event]:
    """Pairs first..last (inclusive) in which nothing moved."""
    return [("pair", s, False) for s in range(first, last + 1)]


def moved(*seqs: int) -> list[Event]:
    return [("pair", s, True) for s in seqs]


def play(gate: GateState, events: Iterable[Event]) -> list[Action]:
    out: list[Action] = []
    for ev in events:
        kind = ev[0]
        if kind == "pair":
            seq, motion = int(ev[1]), bool(ev[2])  # type: ignore[call-overload]
            out += gate.pair(seq, motion, 0.05 if motion else 0.0, seq / HZ)
        elif kind == "cap":
            seq, motion = int(ev[1]), bool(ev[2])  # type: ignore[call-overload]
            out += gate.pair(seq, motion, 0.05 if motion else 0.0, seq / HZ,
                             float(ev[3]))  # type: ignore[arg-type]
        elif kind == "alive":
            out += gate.track_alive(int(ev[1]), float(ev[2]))  # type: ignore[call-overload,arg-type]
        elif kind == "ended":
            out += gate.track_ended(int(ev[1]), float(ev[2]))  # type: ignore[call-overload,arg-type]
        elif kind == "rig":
            out += gate.set_rig_moving(bool(ev[1]), float(ev[2]))  # type: ignore[arg-type]
        elif kind == "tracks":
            out += gate.tracks_alive(int(ev[1]), float(ev[2]))  # type: ignore[call-overload,arg-type]
        elif kind == "tick":
            out += gate.tick(float(ev[1]))  # type: ignore[arg-type]
        else:
            raise TypeError(f"unknown event {ev!r}")
    return out


def fed(actions: Iterable[Action]) -> list[tuple[int, str]]:
    return [(a.seq, a.reason.value) for a in actions if isinstance(a, Feed)]


def gated(actions: Iterable[Action]) -> list[int]:
    return [a.seq for a in actions if isinstance(a, Gated)]


CFG = GateConfig(pre_roll=3, keepalive_s=5.0, hold_s=2.0)
BUSY = GateConfig(pre_roll=3, keepalive_s=5.0, hold_s=2.0, busy_rate_hz=3.0)


def captured(moving: bool, times: Iterable[float]) -> list[Event]:
    """Pairs 0, 1, ... arriving at 10 a second, captured at `times`."""
    return [("cap", s, moving, t) for s, t in enumerate(times)]


@pytest.mark.parametrize(("cfg", "events", "want_fed", "want_gated"), [
    # The first pair is fed (keep-alive): an animal in view from the start is seen.
    (CFG, still(0, 0), [(0, "keepalive")], []),
    # Still scene: one keep-alive pair every 5 s, the rest gated once 3 newer pairs came.
    (CFG, still(0, 119), [(0, "keepalive"), (50, "keepalive"), (100, "keepalive")],
     [s for s in range(1, 117) if s not in (50, 100)]),
    # Motion begins at 10: the 3 pairs before it come first, in order (pre-roll).
    (CFG, still(0, 9) + moved(10), [(0, "keepalive"), (7, "pre_roll"), (8, "pre_roll"),
                                    (9, "pre_roll"), (10, "motion")], [1, 2, 3, 4, 5, 6]),
    # A keep-alive in between: pre-roll still gives the last 3 withheld pairs, in order.
    (CFG, still(0, 50) + moved(51),
     [(0, "keepalive"), (50, "keepalive"), (47, "pre_roll"), (48, "pre_roll"),
      (49, "pre_roll"), (51, "motion")], [s for s in range(1, 47)]),
    # Hold: 2 s after the last motion (t = 0.0) every pair goes on, then the gate closes.
    (CFG, moved(0) + still(1, 24), [(0, "motion")] + [(s, "hold") for s in range(1, 21)],
     [21]),
    # Keep-alive counts from the last pair fed, whatever its reason (hold ended at 2.0 s).
    (CFG, moved(0) + still(1, 75), [(0, "motion")] + [(s, "hold") for s in range(1, 21)]
     + [(70, "keepalive")], [s for s in range(21, 73) if s != 70]),
    # A live track holds the gate open; when it ends, the gate closes at once (5 withheld
    # pairs, the newest 3 kept as pre-roll).
    (CFG, [("alive", 7, 0.0)] + still(0, 9) + [("ended", 7, 0.95)] + still(10, 14),
     [(s, "track") for s in range(10)], [10, 11]),
    # A track whose end was lost expires after its TTL (10 s), by tick.
    (CFG, [("alive", 7, 0.0)] + still(0, 99) + [("tick", 10.5)] + still(105, 109),
     [(s, "track") for s in range(100)], [105, 106]),
    # The normalizer's count of live tracks holds the gate open like a track; its 0 ends
    # the hold at once.
    (CFG, [("tracks", 2, 0.0)] + still(0, 9) + [("tracks", 0, 0.95)] + still(10, 14),
     [(s, "track") for s in range(10)], [10, 11]),
    # Said again every second, the count keeps holding past the TTL (10 s)...
    (CFG, [("tracks", 1, 0.0)] + [e for s in range(0, 130) for e in
                                   ([("tracks", 1, s / HZ)] if s % 10 == 0 else [])
                                   + [("pair", s, False)]] + [("tick", 13.0)] + still(130, 134),
     [(s, "track") for s in range(135)], []),
    # ...but a count not said again expires with its TTL, by tick, like a lost track end.
    (CFG, [("tracks", 1, 0.0)] + still(0, 99) + [("tick", 10.5)] + still(105, 109),
     [(s, "track") for s in range(100)], [105, 106]),
    # No pre-roll: a withheld pair is gated at once.
    (GateConfig(pre_roll=0), still(0, 3), [(0, "keepalive")], [1, 2, 3]),
    # A score under min_score is not motion.
    (GateConfig(pre_roll=0, min_score=0.1), moved(0, 1, 2), [(0, "keepalive")], [1, 2]),
    # Rig moving: the gate is off and feeds everything; kept pre-roll pairs are gated.
    (CFG, still(0, 2) + [("rig", True, 0.25)] + still(3, 5),
     [(0, "keepalive"), (3, "off"), (4, "off"), (5, "off")], [1, 2]),
    # Rig still again: a hold of hold_s while the background is learnt afresh, then gated.
    (CFG, [("rig", True, 0.0)] + still(0, 1) + [("rig", False, 0.15)] + still(2, 26),
     [(0, "off"), (1, "off")] + [(s, "hold") for s in range(2, 22)], [22, 23]),
    # Busy rate 3 pairs/s while moving: the onset and its pre-roll go, then due times step
    # by 1/3 s (one pair in 3 or 4, 3 a second on average); the rest are gated.
    (BUSY, still(0, 4) + moved(*range(5, 25)),
     [(0, "keepalive"), (2, "pre_roll"), (3, "pre_roll"), (4, "pre_roll"), (5, "motion"),
      (9, "motion"), (12, "motion"), (15, "motion"), (19, "motion"), (22, "motion")],
     [1, 6, 7, 8, 10, 11, 13, 14, 16, 17, 18, 20, 21, 23, 24]),
    # The hold is paced the same way...
    (BUSY, moved(0) + still(1, 12), [(0, "motion"), (4, "hold"), (7, "hold"), (10, "hold")],
     [1, 2, 3, 5, 6, 8, 9, 11, 12]),
    # ...and so is a live track.
    (BUSY, [("tracks", 1, 0.0)] + still(0, 10),
     [(0, "track"), (4, "track"), (7, "track"), (10, "track")], [1, 2, 3, 5, 6, 8, 9]),
    # A new onset after the gate closed always goes, however soon after the last pair fed.
    (GateConfig(pre_roll=3, hold_s=0.0, busy_rate_hz=3.0), moved(0) + still(1, 1) + moved(2),
     [(0, "motion"), (1, "pre_roll"), (2, "motion")], []),
    # Capture time paces, not arrival: pairs captured 0.2 s apart (a slower source, or a
    # backlog) at 3 pairs/s are 0, 2, 4, 5 (by arrival at 10 a second it would be 0, 4).
    (BUSY, captured(True, [0.0, 0.2, 0.4, 0.6, 0.8, 1.0]),
     [(0, "motion"), (2, "motion"), (4, "motion"), (5, "motion")], [1, 3]),
    # Capture time that goes back (a source that looped or restarted) starts afresh.
    (BUSY, captured(True, [1.0, 1.1, 0.0, 0.1]), [(0, "motion"), (2, "motion")], [1, 3]),
    # A busy rate under one pair per keep-alive: the keep-alive still goes.
    (GateConfig(pre_roll=0, keepalive_s=1.0, hold_s=5.0, busy_rate_hz=0.5),
     moved(*range(21)), [(0, "motion"), (10, "motion"), (20, "motion")],
     [s for s in range(21) if s not in (0, 10, 20)]),
    # A moving rig turns the gate off: every pair, whatever the busy rate.
    (BUSY, [("rig", True, 0.0)] + moved(0, 1, 2), [(0, "off"), (1, "off"), (2, "off")], []),
])
def test_feeds_and_gates(cfg: GateConfig, events: list[Event], want_fed: list[tuple[int, str]],
                         want_gated: list[int]) -> None:
    actions = play(GateState({"mono": cfg}), events)
    assert fed(actions) == want_fed
    assert gated(actions) == want_gated


def test_pre_roll_comes_before_the_pair_that_moved() -> None:
    actions = play(GateState({"mono": CFG}), still(0, 2) + moved(3))
    assert actions[-3:] == [Feed("mono", 1, actions[-3].reason),  # type: ignore[union-attr]
                            Feed("mono", 2, actions[-2].reason),  # type: ignore[union-attr]
                            Feed("mono", 3, actions[-1].reason)]  # type: ignore[union-attr]
    assert [a.reason.value for a in actions[-3:]] == ["pre_roll", "pre_roll", "motion"]  # type: ignore[union-attr]


def test_every_pair_ends_in_one_feed_or_one_gated() -> None:
    """The ledger adds up per pool: fed + gated + kept = pairs, with two pools' own rules."""
    gate = GateState({"mono": CFG, "stereo": GateConfig(pre_roll=1, keepalive_s=20.0,
                                                        hold_s=0.5), "busy": BUSY})
    events = still(0, 80) + moved(81, 82) + still(83, 200) + [("alive", 1, 15.0)] + \
        still(201, 260) + moved(261) + still(262, 300)
    actions = play(gate, events)
    actions += gate.finish()
    for pool in ("mono", "stereo", "busy"):
        seqs = [a.seq for a in actions if isinstance(a, Feed | Gated) and a.pool == pool]
        assert sorted(seqs) == list(range(301)), pool
        counts = gate.counts()[pool]
        assert sum(counts.fed.values()) + counts.gated == 301
        assert counts.kept == 0
        kept = {a.seq for a in actions if isinstance(a, Keep) and a.pool == pool}
        assert kept <= set(seqs)


def test_rig_moving_says_so_once() -> None:
    gate = GateState({"mono": CFG})
    actions = play(gate, [("rig", True, 0.0)] + still(0, 30) + [("rig", True, 3.5)])
    assert [a for a in actions if isinstance(a, Notice)] == \
        [Notice("motion gate off: the rig moves, every pair is fed")]
    back = play(gate, [("rig", False, 4.0)])
    assert back == [Notice("motion gate on: the rig is still")]


@pytest.mark.parametrize(("kwargs", "error"), [
    ({"pre_roll": -1}, "pre_roll: expected 0..100 pairs, got -1"),  # negative
    ({"keepalive_s": 0.0}, "keepalive_s: expected > 0 s, got 0.0"),  # a keep-alive is a must
    ({"hold_s": -1.0}, "hold_s: expected >= 0 s, got -1.0"),  # negative
    ({"min_score": 1.0}, "min_score: expected 0 <= score < 1, got 1.0"),  # nothing passes
    ({"busy_rate_hz": -1.0}, "busy_rate_hz: expected >= 0 pairs/s, got -1.0"),  # negative
])
def test_config_rejects(kwargs: dict[str, float], error: str) -> None:
    with pytest.raises(ValueError, match=error.replace("(", r"\(")):
        GateConfig(**kwargs)  # type: ignore[arg-type]


@pytest.mark.parametrize(("events", "active", "idle"), [
    # Still: idle all along (the keep-alive is no activity).
    (still(0, 50), 0.0, 5.0),
    # Motion at 10 and its hold of 2 s (to 30): active from pair 10 to 30, the rest idle.
    (still(0, 9) + moved(10) + still(11, 50), 2.1, 2.9),
    # A moving rig: the gate is off, every pair fed, all active.
    ([("rig", True, 0.0)] + still(0, 20), 2.0, 0.0),
])
def test_active_and_idle_time(events: list[Event], active: float, idle: float) -> None:
    """The report's split of a run: seconds the gate was open and seconds it was idle."""
    gate = GateState({"mono": CFG})
    play(gate, events)
    assert (round(gate.active_s, 6), round(gate.idle_s, 6)) == (active, idle)


def test_pairs_the_busy_rate_withholds_count_as_active_time() -> None:
    """The gate is open while an animal moves, however few of its pairs the busy rate lets
    through: the report's active time is the open time, not the fed time."""
    gate = GateState({"mono": BUSY})
    actions = play(gate, moved(*range(21)))
    assert gated(actions)  # the rate withheld some
    assert (round(gate.active_s, 6), round(gate.idle_s, 6)) == (2.0, 0.0)
