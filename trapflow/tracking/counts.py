"""Interval counts, pure: fed each capture time's confirmed tracks by label (the tracker's
`Update.seen`) and the tracks that ended, it closes fixed intervals (aligned to multiples
of the interval from time 0) into per-label visits, MaxN and dwell.

Definitions: a visit is a track, counted in the interval where it was first seen (as
confirmed). MaxN is the largest number of tracks of one label seen at one capture time.
Dwell is the time between a track's consecutive sightings (gaps included, as the tracker
kept the id), added to the interval of the later sighting: a closed interval is never
amended, so the time from a track's last sighting before a boundary to its next one goes to
the new interval (at most one detector gap early), and the sum over intervals is exact.

`News`, fed the same, says what the surface should hear first: a label's first track of
the run, and each time a label's MaxN over the run grows.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass

import msgspec

from trapflow.tracking.tracker import TrackEnd

DEFAULT_INTERVAL_S = 600.0


class LabelCount(msgspec.Struct, frozen=True, kw_only=True):
    """One label's numbers in one interval."""

    label: str
    visits: int
    max_n: int
    dwell_s: float


class IntervalCounts(msgspec.Struct, frozen=True, kw_only=True):
    """One closed interval, as written to counts.jsonl; pairs = capture times fed (effort)."""

    start_s: float
    end_s: float
    pairs: int
    labels: list[LabelCount]


@dataclass
class _Open:
    start_s: float
    pairs: int = 0


class Counter:
    """Accumulates one interval at a time; observe() returns the intervals it closed."""

    def __init__(self, interval_s: float = DEFAULT_INTERVAL_S) -> None:
        if not interval_s > 0:
            raise ValueError(f"interval_s: expected more than 0, got {interval_s}")
        self.interval_s = interval_s
        self._open: _Open | None = None
        self._visits: dict[str, int] = {}
        self._max_n: dict[str, int] = {}
        self._dwell: dict[str, float] = {}
        self._last: dict[int, float] = {}  # track id -> last sighting
        self._known: set[int] = set()  # ids already counted as a visit

    def observe(self, t_s: float, seen: Mapping[str, Collection[int]]) -> list[IntervalCounts]:
        """One capture time's confirmed tracks by label; returns the intervals closed first."""
        closed = self._advance(t_s)
        assert self._open is not None
        self._open.pairs += 1
        for label, ids in seen.items():
            self._max_n[label] = max(self._max_n.get(label, 0), len(ids))
            for tid in ids:
                if tid not in self._known:
                    self._known.add(tid)
                    self._visits[label] = self._visits.get(label, 0) + 1
                elif tid in self._last:
                    self._dwell[label] = self._dwell.get(label, 0.0) + t_s - self._last[tid]
                self._last[tid] = t_s
        return closed

    def ended(self, tracks: Iterable[TrackEnd]) -> None:
        """Forget tracks that ended (they add no more dwell)."""
        for tr in tracks:
            self._last.pop(tr.id, None)
            self._known.discard(tr.id)

    def flush(self, t_s: float) -> list[IntervalCounts]:
        """Close the open interval at t_s (shutdown): its end is t_s, not the boundary.
        End the tracker's tracks first (`ended(tracker.flush(t_s))`)."""
        if self._open is None:
            return []
        out = self._close(min(max(t_s, self._open.start_s), self._open.start_s + self.interval_s))
        self._open = None
        return [out]

    def _advance(self, t_s: float) -> list[IntervalCounts]:
        start = math.floor(t_s / self.interval_s) * self.interval_s
        if self._open is None:
            self._open = _Open(start_s=start)
            return []
        if t_s < self._open.start_s:
            raise ValueError(f"capture times must not go back: got {t_s} in the interval "
                             f"from {self._open.start_s}")
        if start == self._open.start_s:
            return []
        # Intervals with no capture time at all are not written: no effort, no record.
        out = [self._close(self._open.start_s + self.interval_s)]
        self._open = _Open(start_s=start)
        return out

    def _close(self, end_s: float) -> IntervalCounts:
        assert self._open is not None
        labels = sorted(set(self._visits) | set(self._max_n) | set(self._dwell))
        rec = IntervalCounts(start_s=self._open.start_s, end_s=end_s, pairs=self._open.pairs,
                             labels=[LabelCount(label=lb, visits=self._visits.get(lb, 0),
                                                max_n=self._max_n.get(lb, 0),
                                                dwell_s=round(self._dwell.get(lb, 0.0), 3))
                                     for lb in labels])
        self._visits, self._max_n, self._dwell = {}, {}, {}
        return rec


class RunNews(msgspec.Struct, frozen=True, kw_only=True):
    """News the surface should hear first: a label's first confirmed track of the run
    (`new_label`), or a label's MaxN over the run so far grown past 1 (`max_n`)."""

    label: str
    max_n: int  # tracks of the label seen at this capture time (the run's new MaxN)
    new_label: bool
    track: int  # the lowest id among them


class News:
    """The run's news, pure: fed each capture time's confirmed tracks by label, it answers
    when a label is seen for the first time and when a label's run-wide MaxN grows."""

    def __init__(self) -> None:
        self._max_n: dict[str, int] = {}

    def observe(self, seen: Mapping[str, Collection[int]]) -> list[RunNews]:
        """The news of one capture time, by label in name order."""
        out = []
        for label in sorted(seen):
            ids = seen[label]
            before = self._max_n.get(label, 0)
            if len(ids) > before:
                self._max_n[label] = len(ids)
                out.append(RunNews(label=label, max_n=len(ids), new_label=before == 0,
                                   track=min(ids)))
        return out
