"""Interval counts, pure: fed each capture time's confirmed tracks (the tracker's
`Update.seen`, ids only) and the tracks that ended (with their labels), it closes fixed
intervals (aligned to multiples of the interval from time 0) into per-label visits, MaxN and
dwell.

Two clocks: the capture time `t_s` measures (a monotonic clock, or a recording's stamps),
`label_s` names (the pair's wall clock; the same as t_s when one clock does both). An
interval starts at the multiple of the interval at or before its first pair's label, and
closes when its length has passed on the measuring clock, at the next multiple as the label
clock read at its start: with no step of the wall clock that is the next multiple, as
before. When the wall clock steps (an NTP fix after a boot without a real-time clock), the
open interval still closes on elapsed time, and the next one is aligned again to the new
wall clock: its label may then overlap or skip the one before, but every interval lasts at
most `interval_s`, and pairs, visits, MaxN and dwell are counted once each.

One label per track: a track's label is the one its record in tracks.jsonl carries, the
majority of all its boxes (TrackEnd.label), known when it ends. Everything counted per
label waits for it: a closed interval is given out once every track seen in it has ended
(at most `max_gap_s` after the interval, unless an animal stays on), and the news of a
track once it has ended. Before, a visit took the label its track had when it was first
seen (its first box, on a tie at confirmation): a crab track of one scallop box and 52 crab
boxes was counted a scallop.

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
from dataclasses import dataclass, field

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


def _peaks(sets: list[tuple[float, frozenset[int]]], t_s: float, ids: Collection[int]) -> None:
    """Add one capture time's ids to `sets`, unless they are the same as the last added:
    MaxN needs every change of who is in view, not every capture time (an animal that
    stays costs one entry, not one per pair)."""
    if ids and (not sets or sets[-1][1] != ids):
        sets.append((t_s, frozenset(ids)))


def _by_label(ids: Iterable[int], labels: Mapping[int, str]) -> dict[str, list[int]]:
    out: dict[str, list[int]] = {}
    for tid in ids:
        out.setdefault(labels[tid], []).append(tid)
    return out


@dataclass
class _Interval:
    """One interval's numbers by track id, until every track in it has its label."""

    start_s: float  # on the measuring clock
    due_s: float  # when it closes, on the measuring clock
    label_s: float  # its start on the label clock (a multiple of the interval)
    end_s: float | None = None  # None while open
    pairs: int = 0
    visits: set[int] = field(default_factory=set)  # tracks first seen here
    dwell: dict[int, float] = field(default_factory=dict)
    seen: list[tuple[float, frozenset[int]]] = field(default_factory=list)  # who, when

    def ids(self) -> set[int]:
        return set(self.dwell) | self.visits | {i for _t, s in self.seen for i in s}


class Counter:
    """Accumulates one interval at a time by track id; observe(), ended() and flush() return
    the intervals that are closed and whose tracks have all ended, in time order."""

    def __init__(self, interval_s: float = DEFAULT_INTERVAL_S) -> None:
        if not interval_s > 0:
            raise ValueError(f"interval_s: expected more than 0, got {interval_s}")
        self.interval_s = interval_s
        self._intervals: list[_Interval] = []  # closed ones waiting for labels, then the open
        self._last: dict[int, float] = {}  # live track id -> last sighting
        self._labels: dict[int, str] = {}  # ended tracks' labels, while an interval needs them

    def observe(self, t_s: float, seen: Collection[int],
                label_s: float | None = None) -> list[IntervalCounts]:
        """One capture time's confirmed tracks (`t_s` on the measuring clock, `label_s` the
        same instant on the label clock, t_s when None); returns the intervals it let out."""
        self._advance(t_s, t_s if label_s is None else label_s)
        now = self._intervals[-1]
        now.pairs += 1
        _peaks(now.seen, t_s, seen)
        for tid in seen:
            if tid not in self._last and tid not in self._labels:
                now.visits.add(tid)
            elif tid in self._last:
                now.dwell[tid] = now.dwell.get(tid, 0.0) + t_s - self._last[tid]
            self._last[tid] = t_s
        return self._release()

    def ended(self, tracks: Iterable[TrackEnd]) -> list[IntervalCounts]:
        """Tracks that ended, with their labels: they add no more dwell, and the intervals
        that waited for them may go out (returned)."""
        for tr in tracks:
            self._last.pop(tr.id, None)
            self._labels[tr.id] = tr.label
        return self._release()

    def flush(self, t_s: float) -> list[IntervalCounts]:
        """Close the open interval at t_s (shutdown): its end is t_s, not the boundary.
        End the tracker's tracks first (`ended(tracker.flush(t_s))`): every interval then
        goes out."""
        if self._intervals and self._intervals[-1].end_s is None:
            last = self._intervals[-1]
            last.end_s = min(max(t_s, last.start_s), last.due_s)
        out = self._release()
        if self._intervals:
            waiting = sorted(self._intervals[0].ids() - set(self._labels))
            raise ValueError(f"flush: expected every track seen to have ended first, got "
                             f"tracks {waiting} without a label")
        return out

    def _advance(self, t_s: float, label_s: float) -> None:
        last = self._intervals[-1] if self._intervals else None
        if last is not None and last.end_s is None:
            if t_s < last.start_s:
                raise ValueError(f"capture times must not go back: got {t_s} in the interval "
                                 f"from {last.start_s}")
            if t_s < last.due_s:
                return
            # Intervals with no capture time at all are not written: no effort, no record.
            last.end_s = last.due_s
        aligned = math.floor(label_s / self.interval_s) * self.interval_s
        start = t_s - (label_s - aligned)
        if last is not None and last.end_s is not None and start < last.end_s:
            start = last.end_s  # the label clock stepped back: no overlap on the measuring one
        self._intervals.append(_Interval(start_s=start, label_s=label_s - (t_s - start),
                                         due_s=t_s + (aligned + self.interval_s - label_s)))

    def _release(self) -> list[IntervalCounts]:
        out = []
        while self._intervals and self._intervals[0].end_s is not None:
            head = self._intervals[0]
            if not head.ids() <= set(self._labels):
                break  # a track of it is still alive: its label is not known yet
            out.append(self._counts(head))
            self._intervals.pop(0)
        if out:  # forget the labels no waiting interval needs
            needed = set().union(*(iv.ids() for iv in self._intervals))
            self._labels = {k: v for k, v in self._labels.items() if k in needed}
        return out

    def _counts(self, iv: _Interval) -> IntervalCounts:
        assert iv.end_s is not None
        labels = self._labels
        visits = {lb: len(ids) for lb, ids in _by_label(iv.visits, labels).items()}
        dwell: dict[str, float] = {}
        for tid, d in iv.dwell.items():
            dwell[labels[tid]] = dwell.get(labels[tid], 0.0) + d
        max_n: dict[str, int] = {}
        for _t, ids in iv.seen:
            for lb, of in _by_label(ids, labels).items():
                max_n[lb] = max(max_n.get(lb, 0), len(of))
        return IntervalCounts(start_s=iv.label_s, end_s=iv.label_s + (iv.end_s - iv.start_s),
                              pairs=iv.pairs,
                              labels=[LabelCount(label=lb, visits=visits.get(lb, 0),
                                                 max_n=max_n.get(lb, 0),
                                                 dwell_s=round(dwell.get(lb, 0.0), 3))
                                      for lb in sorted(set(visits) | set(max_n) | set(dwell))])


class RunNews(msgspec.Struct, frozen=True, kw_only=True):
    """News the surface should hear first: a label's first confirmed track of the run
    (`new_label`), or a label's MaxN over the run so far grown past 1 (`max_n`)."""

    label: str
    max_n: int  # tracks of the label seen at this capture time (the run's new MaxN)
    new_label: bool
    track: int  # the lowest id among them
    t_s: float  # the capture time they were seen at


class News:
    """The run's news, pure: fed each capture time's confirmed tracks and the tracks that
    ended, it answers when a label is seen for the first time and when a label's run-wide
    MaxN grows. A capture time's tracks count once all of them have ended (their labels
    are then the tracks' own); capture times are taken in time order among those that
    became countable at the same call, so a short visit is news while a long one goes on."""

    def __init__(self) -> None:
        self._max_n: dict[str, int] = {}
        self._waiting: list[tuple[float, frozenset[int]]] = []  # who was seen when
        self._labels: dict[int, str] = {}  # ended tracks' labels, while waiting needs them

    def observe(self, t_s: float, seen: Collection[int]) -> None:
        """One capture time's confirmed tracks (their news comes when they have ended)."""
        _peaks(self._waiting, t_s, seen)

    def ended(self, tracks: Iterable[TrackEnd]) -> list[RunNews]:
        """Tracks that ended, with their labels; returns the news they made known, by
        capture time, then label in name order."""
        for tr in tracks:
            self._labels[tr.id] = tr.label
        out: list[RunNews] = []
        keep: list[tuple[float, frozenset[int]]] = []
        for t_s, ids in self._waiting:
            if not ids <= self._labels.keys():
                keep.append((t_s, ids))
                continue
            for label, of in sorted(_by_label(ids, self._labels).items()):
                before = self._max_n.get(label, 0)
                if len(of) > before:
                    self._max_n[label] = len(of)
                    out.append(RunNews(label=label, max_n=len(of), new_label=before == 0,
                                       track=min(of), t_s=t_s))
        self._waiting = keep
        needed = {i for _t, s in keep for i in s}
        self._labels = {k: v for k, v in self._labels.items() if k in needed}
        return out
