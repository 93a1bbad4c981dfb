"""Interval counts, pure: visits, MaxN and dwell per label, interval boundaries, flush; the
run's news (a label's first track, a new run-wide MaxN)."""

from __future__ import annotations

import pytest

from trapflow.tracking.counts import Counter, IntervalCounts, LabelCount, News, RunNews
from trapflow.tracking.tracker import TrackEnd

Step = tuple[float, dict[str, set[int]]]


def feed(steps: list[Step], interval_s: float = 10.0, flush_at: float | None = None
         ) -> list[IntervalCounts]:
    counter = Counter(interval_s)
    out = []
    for t, seen in steps:
        out += counter.observe(t, seen)
    if flush_at is not None:
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


def test_interval_is_emitted_when_the_next_capture_time_passes_it() -> None:
    counter = Counter(10.0)
    assert counter.observe(9.9, {"crab": {1}}) == []
    closed = counter.observe(10.0, {})
    assert closed == [IntervalCounts(start_s=0.0, end_s=10.0, pairs=1,
                                     labels=[LabelCount(label="crab", visits=1, max_n=1,
                                                        dwell_s=0.0)])]


def test_ended_track_adds_no_dwell_past_its_end() -> None:
    counter = Counter(10.0)
    counter.observe(1.0, {"crab": {1}})
    counter.observe(2.0, {"crab": {1}})
    counter.ended([TrackEnd(id=1, label="crab", label_share=1.0, first_s=1.0, last_s=2.0,
                            pairs=2, best_confidence=0.9, best_box=(0, 0, 1, 1), path=[])])
    (rec,) = counter.observe(25.0, {})
    assert counts(rec) == {"crab": (1, 1, 1.0)}


def test_empty_intervals_are_skipped_and_intervals_align_to_zero() -> None:
    recs = feed([(5.0, {"crab": {1}}), (35.0, {"crab": {2}})], flush_at=36.0)
    assert [(r.start_s, r.end_s) for r in recs] == [(0.0, 10.0), (30.0, 36.0)]
    assert counts(recs[1]) == {"crab": (1, 1, 0.0)}


def test_flush_without_data_returns_nothing() -> None:
    assert Counter().flush(100.0) == []


def test_time_going_back_is_refused() -> None:
    counter = Counter(10.0)
    counter.observe(15.0, {})
    with pytest.raises(ValueError, match="must not go back"):
        counter.observe(5.0, {})


NEWS = [
    # (steps of confirmed tracks by label, expected news per step as (label, max_n, new, id))
    # A label's first track is news once; the same label again is not.
    ([{"crab": {3}}, {"crab": {3}}, {"crab": {4}}], [[("crab", 1, True, 3)], [], []]),
    # Two crabs at once later: the run's MaxN grew; a third time with two is no news.
    ([{"crab": {1}}, {"crab": {1, 2}}, {"crab": {2, 5}}],
     [[("crab", 1, True, 1)], [("crab", 2, False, 1)], []]),
    # First seen two at a time: new label and its MaxN in one, the lowest id named.
    ([{"scallop": {7, 6}}], [[("scallop", 2, True, 6)]]),
    # Labels are news apart, in name order; nobody seen is no news.
    ([{}, {"scallop": {2}, "crab": {1}}, {"crab": {1}, "fish": {9}}],
     [[], [("crab", 1, True, 1), ("scallop", 1, True, 2)], [("fish", 1, True, 9)]]),
    # MaxN falling and rising back to its old height is no news (the run's MaxN, not the
    # interval's).
    ([{"crab": {1, 2}}, {"crab": {1}}, {"crab": {1, 3}}], [[("crab", 2, True, 1)], [], []]),
]


@pytest.mark.parametrize(("steps", "expected"), NEWS)
def test_news_of_the_run(steps: list[dict[str, set[int]]],
                         expected: list[list[tuple[str, int, bool, int]]]) -> None:
    news = News()
    got = [news.observe(seen) for seen in steps]
    assert got == [[RunNews(label=lb, max_n=n, new_label=new, track=tid)
                    for lb, n, new, tid in step] for step in expected]
