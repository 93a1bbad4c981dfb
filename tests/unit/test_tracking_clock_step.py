"""The observation stage under a stepped wall clock: durations, gaps and counting intervals
are measured on the pairs' capture times (a monotonic clock), the wall clock only names
them. Regression: with the wall clock stepped back an hour (an NTP fix after a boot without
a real-time clock) mid-run, tracks lasted 0.0 s or never ended and no interval closed;
stepped forward, an interval was cut short."""

from __future__ import annotations

from typing import Any

import pytest

from trapflow.config.schema import ObserveConfig
from trapflow.tracking.counts import Counter
from trapflow.tracking.stage import Observer

MONO0_NS = 5_000 * 10**9  # the monotonic clock at the first pair
WALL0_NS = 1_764_000_000 * 10**9
STEP_NS = -3600 * 10**9  # the wall clock stepped back an hour
PERIOD_NS = 100_000_000  # 10 Hz


def _box(x: float) -> list[dict[str, Any]]:
    return [{"timestamp": "t", "seq": 0, "label": "crab", "confidence": 0.9,
             "box": [x, 100.0, x + 40.0, 130.0], "v": 2}]


Lines = list[dict[str, Any]]


def _run(step_at: int | None, pairs: int = 200) -> tuple[Lines, Lines]:
    """One crab in view for the first 150 pairs (15 s), then nothing: the wall clock steps at
    pair `step_at`."""
    obs = Observer(ObserveConfig(interval_s=10.0, max_gap_s=1.0))
    tracks: list[dict[str, Any]] = []
    counts: list[dict[str, Any]] = []
    for i in range(pairs):
        mono = MONO0_NS + i * PERIOD_NS
        wall = WALL0_NS + i * PERIOD_NS + (STEP_NS if step_at is not None and i >= step_at else 0)
        got = obs.feed(mono, _box(100.0 + i) if i < 150 else [], wall)
        tracks += [t["track"] for t in got.tracks]
        counts += [c["counts"] for c in got.counts]
    end = obs.finish()
    tracks += [t["track"] for t in end.tracks]
    counts += [c["counts"] for c in end.counts]
    return tracks, counts


def test_a_track_across_a_step_back_lasts_its_real_time_and_ends() -> None:
    tracks, counts = _run(step_at=80)
    (track,) = tracks
    assert track["duration_s"] == pytest.approx(14.9, abs=0.01)  # pairs 0..149
    # Named on the clock after the step (the corrected one): its end is the last pair's.
    last_wall_s = (WALL0_NS + 149 * PERIOD_NS + STEP_NS) / 1e9
    assert track["last_s"] == pytest.approx(last_wall_s, abs=1e-3)
    assert track["path"][-1][0] == pytest.approx(last_wall_s, abs=1e-3)
    # Every pair counted once; intervals close on elapsed time (none longer than 10 s).
    assert sum(c["pairs"] for c in counts) == 200
    assert all(0 < c["end_s"] - c["start_s"] <= 10.0 + 1e-6 for c in counts)
    assert len(counts) >= 2  # intervals closed during the run, not only at its end
    assert sum(lb["visits"] for c in counts for lb in c["labels"]) == 1


def test_without_a_step_intervals_stay_on_wall_multiples() -> None:
    _tracks, counts = _run(step_at=None)
    starts = [c["start_s"] for c in counts]
    assert all(s % 10.0 == pytest.approx(0.0, abs=1e-6) for s in starts)
    assert [c["end_s"] - c["start_s"] for c in counts[:-1]] == [pytest.approx(10.0)] * (
        len(counts) - 1)


def test_counter_closes_on_elapsed_time_when_the_label_steps_forward() -> None:
    """A day's step forward neither closes the open interval early nor counts it twice."""
    counter = Counter(60.0)
    out = counter.observe(0.0, [], 120.0)
    out += counter.observe(30.0, [], 120.0 + 30 + 86_400)  # stepped a day: still open
    assert out == []
    out = counter.observe(60.0, [], 120.0 + 60 + 86_400)  # 60 s elapsed: it closes
    (closed,) = out
    assert (closed.start_s, closed.end_s, closed.pairs) == (120.0, 180.0, 2)
    (last,) = counter.flush(61.0)
    assert last.start_s == 120.0 + 60 + 86_400 and last.pairs == 1
