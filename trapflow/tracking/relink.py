"""Re-linking of broken tracks, an offline pass over the tracker's output, pure.

The tracker ends a track it lost and starts a new one when the animal comes back outside
its gates (a fast turn, a fish that crossed another and was missed for a few frames). Once
both are known, the break is plain to see: one track's boxes stop, another's begin a moment
later near where the first was heading, same label. `link` joins such pieces: a piece that
ended to one that began at most `max_gap_s` seconds (capture time, not frames) after its
last box, never overlapping it in time, of the same label, near the first one's predicted
position; chains are joined too (a piece may have one successor and one predecessor). The
joins are chosen together, the most plausible set (a maximum-weight matching over the
gated pairs), not first come first served.

The distance of a pair: each end's motion carried across the gap (the earlier piece's end
velocity forward, the later piece's start velocity backward), the mean miss of the two,
in box sides (the root of the box area, the mean of the two ends); it is gated at
`gate + gate_per_s * gap` box sides, so a longer gap allows a larger miss.

`Relinker` runs the same pass over a stream of tracked boxes with bounded memory: it
decides the pieces that began before a horizon (the caller holds its output that long),
each time over every piece it knows, so a later piece may take a predecessor that fits it
better; it keeps only the pieces that may still be joined.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from trapflow.tracking.assign import match_edges

Box = tuple[float, float, float, float]

SIZE_RATIO = 2.0
"""Most ratio of the box sides of the two ends of a join (either way)."""


@dataclass(frozen=True)
class RelinkConfig:
    """Limits of a join; defaults chosen on the synthetic development seeds and the crocea
    set together (docs/benchmarks.md, "Tracking"; the pass is off by default in `trapflow
    track`: it lost on the held-out synthetic worlds)."""

    max_gap_s: float = 1.0
    """Longest time from a piece's last box to the next piece's first box."""
    gate: float = 3.0
    """Largest miss of a join across no gap, in box sides."""
    gate_per_s: float = 4.0
    """Added to the gate per second of gap, in box sides."""
    velocity_s: float = 0.5
    """A piece's end (start) velocity is fitted to its boxes of its last (first) this
    many seconds."""

    def __post_init__(self) -> None:
        if not self.max_gap_s > 0 or not self.gate > 0 or self.gate_per_s < 0:
            raise ValueError(f"expected max_gap_s > 0, gate > 0, gate_per_s >= 0, got "
                             f"{self.max_gap_s}, {self.gate}, {self.gate_per_s}")
        if not self.velocity_s > 0:
            raise ValueError(f"velocity_s: expected > 0, got {self.velocity_s}")


@dataclass(frozen=True)
class Piece:
    """One track as the pass sees it: its label, the time, box (x1, y1, x2, y2) and
    velocity (px/s of the box centre) of its first and of its last box."""

    id: int
    label: str
    first_s: float
    first_box: Box
    first_v: tuple[float, float]
    last_s: float
    last_box: Box
    last_v: tuple[float, float]


def _centre(box: Box) -> tuple[float, float]:
    return (box[0] + box[2]) / 2, (box[1] + box[3]) / 2


def _side(box: Box) -> float:
    return math.sqrt(max(box[2] - box[0], 0.0) * max(box[3] - box[1], 0.0))


def join_cost(a: Piece, b: Piece, cfg: RelinkConfig) -> float | None:
    """The miss of joining piece a to the later piece b over the gate (in (0, 1]: 1 is at
    the gate), None when they may not be joined."""
    gap = b.first_s - a.last_s
    if a.label != b.label or not 0 < gap <= cfg.max_gap_s:
        return None
    sa, sb = _side(a.last_box), _side(b.first_box)
    if sa <= 0 or sb <= 0 or max(sa / sb, sb / sa) > SIZE_RATIO:
        return None
    (ax, ay), (bx, by) = _centre(a.last_box), _centre(b.first_box)
    fwd = math.hypot(ax + a.last_v[0] * gap - bx, ay + a.last_v[1] * gap - by)
    back = math.hypot(bx - b.first_v[0] * gap - ax, by - b.first_v[1] * gap - ay)
    miss = (fwd + back) / 2 / ((sa + sb) / 2)
    cost = miss / (cfg.gate + cfg.gate_per_s * gap)
    return cost if cost <= 1.0 else None


def link(pieces: Sequence[Piece], cfg: RelinkConfig,
         successors: Sequence[Piece] | None = None) -> list[tuple[int, int]]:
    """The joins (earlier id, later id), sorted: a maximum-weight matching of each piece to
    at most one successor (weight 2 - cost: any join weighs more than none, a closer one
    more). `successors`: the pieces that may be the later one of a join (default: all)."""
    later = list(pieces if successors is None else successors)
    if not pieces or not later:
        return []
    # Only pairs near in time can join: sort the successors by start, look at a window.
    later.sort(key=lambda p: p.first_s)
    starts = np.array([p.first_s for p in later])
    rows: list[int] = []
    cols: list[int] = []
    weight: list[float] = []
    for i, a in enumerate(pieces):
        lo = int(np.searchsorted(starts, a.last_s, side="right"))
        hi = int(np.searchsorted(starts, a.last_s + cfg.max_gap_s, side="right"))
        for j in range(lo, hi):
            cost = join_cost(a, later[j], cfg)
            if cost is not None:
                rows.append(i)
                cols.append(j)
                weight.append(2.0 - cost)
    got = match_edges(len(pieces), len(later), np.array(rows, dtype=np.int64),
                      np.array(cols, dtype=np.int64), np.array(weight))
    return sorted((pieces[i].id, later[j].id) for i, j in got)


def roots(joins: Iterable[tuple[int, int]]) -> dict[int, int]:
    """For each later piece of a join, the id of its chain's first piece."""
    before = dict((b, a) for a, b in joins)
    out: dict[int, int] = {}
    for b in before:
        a = before[b]
        while a in before:
            a = before[a]
        out[b] = a
    return out


class _Seen:
    """The boxes of one track the pass keeps: its first ones and its latest ones (each
    within velocity_s), and its label counts."""

    def __init__(self, t_s: float, box: Box) -> None:
        self.first: list[tuple[float, Box]] = [(t_s, box)]
        self.last: deque[tuple[float, Box]] = deque([(t_s, box)])
        self.labels: dict[str, int] = {}

    def add(self, t_s: float, box: Box, span_s: float) -> None:
        if t_s - self.first[0][0] <= span_s:
            self.first.append((t_s, box))
        self.last.append((t_s, box))
        while t_s - self.last[0][0] > span_s:
            self.last.popleft()

    def piece(self, tid: int) -> Piece:
        # Ties go to the label seen first (dicts keep insertion order), as the tracker's.
        label = max(self.labels, key=lambda k: self.labels[k])
        return Piece(id=tid, label=label, first_s=self.first[0][0], first_box=self.first[0][1],
                     first_v=_velocity(self.first), last_s=self.last[-1][0],
                     last_box=self.last[-1][1], last_v=_velocity(list(self.last)))


def _velocity(seen: Sequence[tuple[float, Box]]) -> tuple[float, float]:
    """The least-squares slope of the box centre over time, px/s (0 from a single time)."""
    t = np.array([s for s, _ in seen])
    if len(t) < 2 or t[-1] - t[0] <= 0:
        return 0.0, 0.0
    c = np.array([_centre(b) for _, b in seen])
    dt = t - t.mean()
    slope = dt @ (c - c.mean(axis=0)) / (dt @ dt)
    return float(slope[0]), float(slope[1])


class Relinker:
    """The pass over a stream: add() each capture time's tracked boxes in time order,
    decide(horizon) when every piece with a box before `horizon` has ended (its boxes
    stopped, or the tracker would have matched more), id() the id to write for a track
    whose boxes are all before the horizon decided last."""

    def __init__(self, config: RelinkConfig | None = None) -> None:
        self.config = config or RelinkConfig()
        self._seen: dict[int, _Seen] = {}
        self._undecided: set[int] = set()  # pieces that may still be the later one
        self._taken: set[int] = set()  # pieces that have their successor
        self._root: dict[int, int] = {}  # id -> the id written, for joined pieces
        self._drop: list[int] = []  # pieces forgotten at the last decide()
        self.joins = 0

    def add(self, t_s: float, boxes: Iterable[tuple[int, str, Box]]) -> None:
        """The boxes a capture time gave, with their track ids and labels."""
        span = self.config.velocity_s
        for tid, label, box in boxes:
            seen = self._seen.get(tid)
            if seen is None:
                seen = self._seen[tid] = _Seen(t_s, box)
                self._undecided.add(tid)
            else:
                seen.add(t_s, box, span)
            seen.labels[label] = seen.labels.get(label, 0) + 1

    def decide(self, horizon_s: float) -> None:
        """Decide every piece that began at or before horizon_s; forget the pieces that
        can no longer be joined either way. The ids of pieces forgotten here stay right
        until the next call (the caller writes their last boxes in between)."""
        cfg = self.config
        for tid in self._drop:
            self._root.pop(tid, None)
        self._drop = []
        now = {tid for tid in self._undecided if self._seen[tid].first[0][0] <= horizon_s}
        if now:
            later = [self._seen[t].piece(t) for t in self._undecided]
            earlier = [s.piece(tid) for tid, s in self._seen.items()
                       if tid not in self._taken and s.last[-1][0] < horizon_s]
            for a, b in link(earlier, cfg, later):
                if b in now:
                    self._root[b] = self._root.get(a, a)
                    self._taken.add(a)
                    self.joins += 1
            self._undecided -= now
        # A piece is done once it has been decided as the later one and it can take no
        # successor (taken, or every piece that began within max_gap_s of its end has been
        # decided).
        done = [tid for tid, s in self._seen.items() if tid not in self._undecided and (
            tid in self._taken or s.last[-1][0] + cfg.max_gap_s < horizon_s)]
        for tid in done:
            del self._seen[tid]
            self._taken.discard(tid)
        self._drop = done

    def id(self, tid: int) -> int:
        """The id to write for track tid."""
        return self._root.get(tid, tid)

    @property
    def held(self) -> int:
        """Pieces kept (for the memory bound)."""
        return len(self._seen)
