"""The multi-object tracker, pure: detections of one capture time in, track ids and ended
tracks out. ByteTrack's association (high-confidence detections first, then low-confidence
ones against the tracks left) over a continuous-time Kalman filter; the caller passes each
pair's capture time, since the detector may see one pair in three or fewer, irregularly.

Lifecycle: an unmatched high-confidence detection starts a tentative track; it is confirmed
(and given the next id) at `min_hits` matches, and is dropped unreported when it went
`tentative_gap_s` without a match before that. A confirmed track ends when it went
`max_gap_s` seconds without a match, or at `flush`; only confirmed tracks are reported.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import msgspec
import numpy as np

from trapflow.tracking.assign import iou_pairs, match_edges
from trapflow.tracking.kalman import (
    BoxFilter,
    Noise,
    distance2_many,
    predict_many,
    update_many,
)

Box = tuple[float, float, float, float]


class Det(msgspec.Struct, frozen=True, kw_only=True):
    """One detection: label, confidence in [0, 1], box x1 y1 x2 y2 in pixels."""

    label: str
    confidence: float
    box: Box


class TrackEnd(msgspec.Struct, frozen=True, kw_only=True):
    """A finished track, as written to tracks.jsonl (times are capture times in s)."""

    id: int
    label: str
    label_share: float  # share of the track's detections that carried `label`
    first_s: float
    last_s: float
    pairs: int  # pairs in which the track was detected
    best_confidence: float
    best_box: Box
    path: list[tuple[float, float, float]]  # (t_s, cx, cy), decimated to <= path_points


@dataclass(frozen=True)
class Update:
    """What one call decided.

    track_ids[i] is the id of detection i's track, or None when the detection started or
    extended a tentative track, or matched nothing. seen: the confirmed tracks matched at
    this capture time (the input of interval counts and news), without labels: a track's
    label is decided once, at its end (TrackEnd.label, the majority of all its boxes).
    ended lists the tracks that ended at this call. capped: detections left out of this
    call because more than `max_boxes` came (the least confident; their ids are None).
    """

    track_ids: tuple[int | None, ...]
    seen: frozenset[int]
    ended: tuple[TrackEnd, ...]
    capped: int = 0


@dataclass(frozen=True)
class TrackerConfig:
    """Thresholds of the tracker; defaults tuned on development seeds only, never on the
    bench's held-out ones: the 16 of the synthetic bench's fake detections
    (benchmarks/tune_tracking.py: mean of HOTA and IDF1 at full detector rate and at one pair
    in three), and live runs' detections of development seeds at policy `latest` with a
    slow detector (docs/benchmarks.md, "Tracking inside a live run")."""

    high: float = 0.5
    """Detections at or above this confidence are matched first and may start tracks."""
    low: float = 0.1
    """Detections below this confidence are ignored; between low and high they may only
    extend a track that the high ones left unmatched."""
    iou_gate: float = 0.1
    """Least IoU between a track's predicted box and a detection for them to match."""
    dist_gate: float = 13.0
    """Second chance for the tracks and high-confidence detections that IoU left apart:
    matched when the detected box is within this squared Mahalanobis distance of the
    track's predicted box (centre and size, 4 degrees of freedom: 13 keeps 99 % of a
    track's own boxes). Its covariance grows with the time unseen, so the gate widens
    across the gaps of a detector that sees one pair in three or fewer, where an animal
    may have moved off its predicted box; 0: off."""
    dup_iou: float = 0.6
    """A detection overlapping a more confident one of the same capture time by at least
    this IoU is left out, whatever the labels (the detector's second label for one animal,
    which would otherwise start or extend a second track); 1: off."""
    min_hits: int = 2
    """Matches that confirm a tentative track and give it an id."""
    max_gap_s: float = 3.0
    """A confirmed track with no match for longer than this (capture time) ends."""
    tentative_gap_s: float = 1.0
    """A tentative track with no match for longer than this is dropped unreported (0: at
    its first miss, as ByteTrack drops unconfirmed tracks)."""
    path_points: int = 32
    """Most box centres kept in a finished track's path."""
    max_boxes: int = 300
    """Most detections one call takes, the most confident (ties: the earlier); the rest
    get no track. Bounds one call's work: a detector returning 10,000 boxes a pair
    stalled the normalizer (issue 36 item 1)."""
    noise: Noise = field(default_factory=Noise)
    """The motion model's noise levels."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.low <= self.high <= 1.0:
            raise ValueError(f"expected 0 <= low <= high <= 1, got low={self.low} "
                             f"high={self.high}")
        if not 0.0 < self.iou_gate < 1.0:
            raise ValueError(f"iou_gate: expected in (0, 1), got {self.iou_gate}")
        if self.dist_gate < 0:
            raise ValueError(f"dist_gate: expected >= 0 (0: off), got {self.dist_gate}")
        if not 0.0 < self.dup_iou <= 1.0:
            raise ValueError(f"dup_iou: expected in (0, 1] (1: off), got {self.dup_iou}")
        if self.max_boxes < 1:
            raise ValueError(f"max_boxes: expected >= 1, got {self.max_boxes}")
        if self.min_hits < 1 or self.max_gap_s <= 0 or self.path_points < 2:
            raise ValueError(f"expected min_hits >= 1, max_gap_s > 0, path_points >= 2, got "
                             f"{self.min_hits}, {self.max_gap_s}, {self.path_points}")


class _Track:
    """One track's mutable state (private to the tracker)."""

    def __init__(self, det: Det, t_s: float, cfg: TrackerConfig) -> None:
        self.id: int | None = None
        self.filter = BoxFilter(np.asarray(det.box, dtype=float), cfg.noise)
        self.t_filter = t_s  # capture time the filter state refers to
        self.first_s = self.last_s = t_s
        self.hits = 0
        self.labels: dict[str, int] = {}
        self.best_confidence = -1.0
        self.best_box: Box = det.box
        self.path: list[tuple[float, float, float]] = []
        self.stride = 1
        self.latest = (t_s, 0.0, 0.0)
        self.record(det, t_s, cfg.path_points)

    def record(self, det: Det, t_s: float, keep: int) -> None:
        self.hits += 1
        self.last_s = t_s
        self.labels[det.label] = self.labels.get(det.label, 0) + 1
        if det.confidence > self.best_confidence:
            self.best_confidence, self.best_box = det.confidence, det.box
        x1, y1, x2, y2 = det.box
        self.latest = (t_s, (x1 + x2) / 2, (y1 + y2) / 2)
        # Bounded memory, evenly spaced: keep every stride-th sighting, and when the path
        # is full keep every other one and double the stride. The newest is kept apart.
        if (self.hits - 1) % self.stride == 0:
            self.path.append(self.latest)
            if len(self.path) >= 2 * keep:
                self.path = self.path[::2]
                self.stride *= 2

    def label(self) -> tuple[str, float]:
        # Ties go to the label seen first (dicts keep insertion order): deterministic.
        best = max(self.labels, key=lambda k: self.labels[k])
        return best, self.labels[best] / self.hits

    def end(self, keep: int) -> TrackEnd:
        assert self.id is not None
        label, share = self.label()
        path = self.path if self.path[-1] == self.latest else [*self.path, self.latest]
        idx = np.unique(np.linspace(0, len(path) - 1, min(keep, len(path))).round().astype(int))
        return TrackEnd(id=self.id, label=label, label_share=round(share, 4),
                        first_s=self.first_s, last_s=self.last_s, pairs=self.hits,
                        best_confidence=self.best_confidence, best_box=self.best_box,
                        path=[path[i] for i in idx])


class Tracker:
    """Tracks across capture times; update() once per pair the detector saw, in time order."""

    def __init__(self, config: TrackerConfig | None = None) -> None:
        self.config = config or TrackerConfig()
        self._tracks: list[_Track] = []
        self._next_id = 1
        self._t: float | None = None

    def update(self, t_s: float, detections: Sequence[Det]) -> Update:
        """Associate the detections of the pair captured at t_s (not before the last call)."""
        cfg = self.config
        if self._t is not None and t_s < self._t:
            raise ValueError(f"capture times must not go back: got {t_s} after {self._t}")
        self._t = t_s
        ended = self._end_stale(t_s)
        predict_many([tr.filter for tr in self._tracks],
                     np.array([t_s - tr.t_filter for tr in self._tracks]))
        for tr in self._tracks:
            tr.t_filter = t_s
        ids: list[int | None] = [None] * len(detections)
        taken = _most_confident(detections, cfg.max_boxes)
        kept = _distinct(detections, taken, cfg.dup_iou)
        high = [i for i in kept if detections[i].confidence >= cfg.high]
        low = [i for i in kept if cfg.low <= detections[i].confidence < cfg.high]
        # Stage 1: high-confidence detections against every track, confirmed or not.
        everyone = list(range(len(self._tracks)))
        pairs, left_tracks, left_high = self._match(everyone, high, detections)
        if cfg.dist_gate > 0:
            more, left_tracks, left_high = self._match_near(left_tracks, left_high, detections)
            pairs += more
        # Stage 2: low-confidence detections only against confirmed tracks left over; a
        # tentative track fed by weak boxes would confirm clutter.
        confirmed_left = [k for k in left_tracks if self._tracks[k].id is not None]
        pairs2, _, _ = self._match(confirmed_left, low, detections)
        matched: dict[int, _Track] = {}
        update_many([self._tracks[k].filter for k, _ in pairs + pairs2],
                    np.array([detections[i].box for _, i in pairs + pairs2], dtype=float))
        for k, i in pairs + pairs2:
            tr = self._tracks[k]
            tr.record(detections[i], t_s, cfg.path_points)
            if tr.id is None and tr.hits >= cfg.min_hits:
                tr.id, self._next_id = self._next_id, self._next_id + 1
            ids[i] = tr.id
            matched[k] = tr
        # A tentative track not seen for a while is dropped: most likely clutter.
        keep = [tr for k, tr in enumerate(self._tracks) if k in matched or tr.id is not None
                or t_s - tr.last_s <= cfg.tentative_gap_s]
        for i in left_high:
            keep.append(_Track(detections[i], t_s, cfg))
            if cfg.min_hits <= 1:
                keep[-1].id, self._next_id = self._next_id, self._next_id + 1
                ids[i] = keep[-1].id
        self._tracks = keep
        seen = frozenset(tr.id for tr in matched.values() if tr.id is not None)
        return Update(track_ids=tuple(ids), seen=seen, ended=tuple(ended),
                      capped=len(detections) - len(taken))

    def flush(self, t_s: float) -> tuple[TrackEnd, ...]:
        """End every confirmed track (at shutdown); tentative ones are forgotten."""
        del t_s  # the tracks end at their last match, whatever the time now
        out = tuple(tr.end(self.config.path_points) for tr in self._tracks if tr.id is not None)
        self._tracks = []
        return tuple(sorted(out, key=lambda e: e.id))

    @property
    def alive(self) -> int:
        """Confirmed tracks not yet ended."""
        return sum(tr.id is not None for tr in self._tracks)

    def _end_stale(self, t_s: float) -> list[TrackEnd]:
        gap = self.config.max_gap_s
        out = [tr.end(self.config.path_points) for tr in self._tracks
               if tr.id is not None and t_s - tr.last_s > gap]
        self._tracks = [tr for tr in self._tracks if tr.id is None or t_s - tr.last_s <= gap]
        return sorted(out, key=lambda e: e.id)

    def _match_near(self, tracks: list[int], dets: list[int], detections: Sequence[Det]
                    ) -> tuple[list[tuple[int, int]], list[int], list[int]]:
        """Minimum-cost matching on the squared Mahalanobis distance under dist_gate."""
        if not tracks or not dets:
            return [], list(tracks), list(dets)
        boxes = np.array([detections[i].box for i in dets], dtype=float)
        d2 = distance2_many([self._tracks[k].filter for k in tracks], boxes)
        gate = self.config.dist_gate
        r, c = np.nonzero(d2 <= gate)
        # A pair under the gate weighs more the closer it is; any weighs more than none.
        got = match_edges(len(tracks), len(dets), r, c, gate * 2.0 + 1.0 - d2[r, c])
        return _split(tracks, dets, [(tracks[a], dets[b]) for a, b in got])

    def _match(self, tracks: list[int], dets: list[int], detections: Sequence[Det]
               ) -> tuple[list[tuple[int, int]], list[int], list[int]]:
        """Minimum-cost (1 - IoU) matching under the IoU gate; returns the matched
        (track index, detection index) pairs, the tracks and detections left."""
        if not tracks or not dets:
            return [], list(tracks), list(dets)
        pred = np.array([self._tracks[k].filter.box() for k in tracks])
        boxes = np.array([detections[i].box for i in dets], dtype=float)
        # Only pairs over the gate may match: the most total IoU among them, which is
        # the least total (1 - IoU) cost over the whole matrix with a gated pair at 1.
        r, c, iou = iou_pairs(pred, boxes, self.config.iou_gate)
        got = match_edges(len(tracks), len(dets), r, c, iou)
        return _split(tracks, dets, [(tracks[a], dets[b]) for a, b in got])


def _split(tracks: list[int], dets: list[int], pairs: list[tuple[int, int]]
           ) -> tuple[list[tuple[int, int]], list[int], list[int]]:
    """The matched pairs, and the tracks and detections they leave."""
    used_t = {k for k, _ in pairs}
    used_d = {i for _, i in pairs}
    return (pairs, [k for k in tracks if k not in used_t], [i for i in dets if i not in used_d])


def _most_confident(detections: Sequence[Det], most: int) -> list[int]:
    """Indices of the `most` most confident detections (ties to the earlier), in order."""
    if len(detections) <= most:
        return list(range(len(detections)))
    conf = np.array([d.confidence for d in detections], dtype=float)
    return sorted(np.argsort(-conf, kind="stable")[:most].tolist())


def _distinct(detections: Sequence[Det], taken: list[int], dup_iou: float) -> list[int]:
    """Of the detections `taken`, those that overlap no more confident one by dup_iou or
    more (greedy, most confident first; ties to the earlier detection), in their order.
    Only overlapping pairs are looked at, never an N x N matrix (issue 36 item 1)."""
    if dup_iou >= 1.0 or len(taken) < 2:
        return list(taken)
    boxes = np.array([detections[i].box for i in taken], dtype=float)
    conf = np.array([detections[i].confidence for i in taken], dtype=float)
    rank = np.empty(len(taken), dtype=np.int64)
    rank[np.argsort(-conf, kind="stable")] = np.arange(len(taken))
    r, c, _ = iou_pairs(boxes, boxes, dup_iou)
    # Each overlap once, from the more confident box to the one it may leave out.
    keep = rank[r] < rank[c]
    r, c = r[keep], c[keep]
    if len(r) == 0:
        return list(taken)
    out = np.ones(len(taken), dtype=bool)
    # Grouped by the more confident box, the groups in confidence order: a box still kept
    # when its group comes (no kept box above it overlaps it) leaves out its group.
    order = np.argsort(rank[r], kind="stable")
    r, c = r[order], c[order]
    _, starts = np.unique(rank[r], return_index=True)
    for s, e in zip(starts.tolist(), [*starts[1:].tolist(), len(r)], strict=True):
        if out[r[s]]:
            out[c[s:e]] = False
    return [taken[k] for k in np.flatnonzero(out)]
