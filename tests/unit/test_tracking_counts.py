"""Interval counts, pure: visits, MaxN and dwell per label, interval boundaries, flush; the
run's news (a label's first track, a new run-wide MaxN)."""

from __future__ import annotations

import pytest

from trapflow.tracking.counts import Counter, IntervalCounts, LabelCount, News, RunNews
from trapflow.tracking.tracker import TrackEnd

Step = tuple[float, dict[str, set[int]]]


def end(tid: int, label: str) -> TrackEnd:
    return TrackEnd(id=tid, label=label, label_share=1.0, first_s=0.0, last_s=0.0, pairs=1,
                    best_confidence=0.9, best_box=(0, 0, 1, 1), path=[])


def feed(steps: list[Step], interval_s: float = 10.0, flush_at: float | None = None
         ) -> list[IntervalCounts]:
    """Steps of confirmed tracks grouped by the label each track ends with; at flush_at every
    track ends with that label, then the open interval closes."""
    counter = Counter(interval_s)
    labels = {tid: lb for _t, seen in steps for lb, ids in seen.items() for tid in ids}
    out = []
    for t, seen in steps:
        out += counter.observe(t, {tid for ids in seen.values() for tid in ids})
    if flush_at is not None:
        out += counter.ended([end(tid, lb) for tid, lb in sorted(labels.items())])
        out += counter.flush(flush_at)
    return out


def counts(rec: IntervalCounts) -> dict[str, tuple[int, int, float]]:
    return {c.label: (c.visits, c.max_n, c.dwell_s) for c in rec.labels}


ONE_INTERVAL = [
    # (steps, expected per label: visits, MaxN, dwell_s)
    # One crab seen at 1, 2 and 4 s: one visit, MaxN 1, dwell 3 s (the gap counts).
    ([(1.0, {"crab": {1}}), (2.0, {"crab": {1}}), (4.0, {"crab": {1}})],
     {"crab": (1, 1, 3.0)}),
    # Two crabs overlap at 2 s: MaxN 2; visits 2; dwell 1 + 1.
    ([(1.0, {"crab": {1}}), (2.0, {"crab": {1, 2}}), (3.0, {"crab": {2}})],
     {"crab": (2, 2, 2.0)}),
    # Three crabs one after another, never together: MaxN 1, three visits.
    ([(1.0, {"crab": {1}}), (2.0, {"crab": {2}}), (3.0, {"crab": {3}})],
     {"crab": (3, 1, 0.0)}),
    # Labels are counted apart.
    ([(1.0, {"crab": {1}, "scallop": {2, 3}}), (1.5, {"scallop": {2, 3}})],
     {"crab": (1, 1, 0.0), "scallop": (2, 2, 1.0)}),
    # A capture time with nobody seen still counts as effort, adds nothing.
    ([(1.0, {}), (2.0, {})], {}),
]


@pytest.mark.parametrize(("steps", "expected"), ONE_INTERVAL)
def test_visits_maxn_and_dwell(steps: list[Step], expected: dict[str, tuple[int, int, float]]
                               ) -> None:
    (rec,) = feed(steps, flush_at=5.0)
    assert counts(rec) == expected
    assert rec.pairs == len(steps)


def test_interval_closes_at_the_boundary_and_splits_dwell() -> None:
    """A crab seen at 8, 9, 11 and 13 s: 1 s of dwell in [0, 10), 4 s in [10, 20) (9 to 11
    goes to the later sighting's interval); one visit, counted where it was first seen."""
    recs = feed([(8.0, {"crab": {1}}), (9.0, {"crab": {1}}), (11.0, {"crab": {1}}),
                 (13.0, {"crab": {1}})], flush_at=14.0)
    assert [(r.start_s, r.end_s, r.pairs) for r in recs] == [(0.0, 10.0, 2), (10.0, 14.0, 2)]
    assert counts(recs[0]) == {"crab": (1, 1, 1.0)}
    assert counts(recs[1]) == {"crab": (0, 1, 4.0)}


def test_interval_goes_out_once_closed_and_its_tracks_have_ended() -> None:
    """An interval closed by a later capture time waits for its live tracks' labels."""
    counter = Counter(10.0)
    assert counter.observe(9.9, {1}) == []
    assert counter.observe(10.0, set()) == []  # closed, but track 1 goes on
    closed = counter.ended([end(1, "crab")])
    assert closed == [IntervalCounts(start_s=0.0, end_s=10.0, pairs=1,
                                     labels=[LabelCount(label="crab", visits=1, max_n=1,
                                                        dwell_s=0.0)])]


def test_ended_track_adds_no_dwell_past_its_end() -> None:
    counter = Counter(10.0)
    counter.observe(1.0, {1})
    counter.observe(2.0, {1})
    assert counter.ended([end(1, "crab")]) == []  # its interval is still open
    (rec,) = counter.observe(25.0, set())
    assert counts(rec) == {"crab": (1, 1, 1.0)}


def test_intervals_go_out_in_order_behind_a_long_track() -> None:
    """A long track holds its interval and every later one back; they go out together, in
    time order, when it ends."""
    counter = Counter(10.0)
    counter.observe(5.0, {1})
    counter.observe(15.0, {1, 2})
    assert counter.ended([end(2, "fish")]) == []
    assert counter.observe(25.0, {1}) == []
    recs = counter.ended([end(1, "crab")])
    assert [r.start_s for r in recs] == [0.0, 10.0]
    assert counts(recs[1]) == {"crab": (0, 1, 10.0), "fish": (1, 1, 0.0)}
    (last,) = counter.flush(26.0)
    assert counts(last) == {"crab": (0, 1, 10.0)}


def test_a_visit_takes_the_label_its_track_ends_with() -> None:
    """Regression: a visit took the label of its track's first box; a crab track of one
    scallop box and 52 crab boxes was "scallop: 1 visit, MaxN 1". Ids are counted, and
    labelled when the track ends with its majority label."""
    counter = Counter(600.0)
    for k in range(53):
        counter.observe(k * 0.1, {1})
    (rec,) = counter.ended([end(1, "crab")]) + counter.flush(10.0)
    assert counts(rec) == {"crab": (1, 1, 5.2)}


def test_flush_before_the_tracks_ended_is_refused() -> None:
    counter = Counter(10.0)
    counter.observe(1.0, {4})
    with pytest.raises(ValueError, match=r"every track seen to have ended first, got tracks \[4\]"):
        counter.flush(2.0)


def test_empty_intervals_are_skipped_and_intervals_align_to_zero() -> None:
    recs = feed([(5.0, {"crab": {1}}), (35.0, {"crab": {2}})], flush_at=36.0)
    assert [(r.start_s, r.end_s) for r in recs] == [(0.0, 10.0), (30.0, 36.0)]
    assert counts(recs[1]) == {"crab": (1, 1, 0.0)}


def test_flush_without_data_returns_nothing() -> None:
    assert Counter().flush(100.0) == []


def test_time_going_back_is_refused() -> None:
    counter = Counter(10.0)
    counter.observe(15.0, set())
    with pytest.raises(ValueError, match="must not go back"):
        counter.observe(5.0, set())


NEWS = [
    # (steps: (capture time, confirmed ids, tracks that ended then as {id: label}),
    #  expected news per step as (label, max_n, new, id, time))
    # A label's first track is news once, when it ends; the same label again is not.
    ([(1.0, {3}, {}), (2.0, {3}, {}), (3.0, {4}, {3: "crab"}), (9.0, set(), {4: "crab"})],
     [[], [], [("crab", 1, True, 3, 1.0)], []]),
    # Two crabs at once: the run's MaxN grew, known when both have ended.
    ([(1.0, {1}, {}), (2.0, {1, 2}, {}), (3.0, {2}, {1: "crab"}), (9.0, set(), {2: "crab"})],
     [[], [], [("crab", 1, True, 1, 1.0)], [("crab", 2, False, 1, 2.0)]]),
    # First seen two at a time: new label and its MaxN in one, the lowest id named.
    ([(1.0, {7, 6}, {}), (9.0, set(), {6: "scallop", 7: "scallop"})],
     [[], [("scallop", 2, True, 6, 1.0)]]),
    # Labels are news apart, in name order; nobody seen is no news.
    ([(1.0, set(), {}), (2.0, {2, 1}, {}), (9.0, set(), {1: "crab", 2: "scallop"})],
     [[], [], [("crab", 1, True, 1, 2.0), ("scallop", 1, True, 2, 2.0)]]),
    # A short visit is news while a long one goes on; the long one's label when it ends.
    ([(1.0, {1}, {}), (2.0, {1, 2}, {}), (3.0, {1}, {2: "fish"}), (9.0, set(), {1: "crab"})],
     [[], [], [], [("crab", 1, True, 1, 1.0), ("fish", 1, True, 2, 2.0)]]),
    # The label is the track's own at its end, not its first box's.
    ([(1.0, {5}, {}), (9.0, set(), {5: "crab"})], [[], [("crab", 1, True, 5, 1.0)]]),
]


@pytest.mark.parametrize(("steps", "expected"), NEWS)
def test_news_of_the_run(steps: list[tuple[float, set[int], dict[int, str]]],
                         expected: list[list[tuple[str, int, bool, int, float]]]) -> None:
    news = News()
    got = []
    for t, seen, ended in steps:
        got.append(news.ended([end(tid, lb) for tid, lb in sorted(ended.items())]))
        news.observe(t, seen)
    assert got == [[RunNews(label=lb, max_n=n, new_label=new, track=tid, t_s=ts)
                    for lb, n, new, tid, ts in step] for step in expected]
