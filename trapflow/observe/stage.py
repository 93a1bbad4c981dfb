"""The observation stage, pure: mono detections in (as the normalizer made them), track ids
on them, and the finished tracks and closed intervals out as JSON-able objects.

The normalizer runs it in its own process, on results as they arrive: lines are written at
once, never held back. Results of a pool with several workers can arrive slightly out of
capture order; such a result is tracked at the newest capture time seen (its motion
prediction is a few tens of ms off, well inside the IoU gate), not dropped.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import msgspec

from trapflow.config.schema import ObserveConfig
from trapflow.observe.counts import Counter, IntervalCounts
from trapflow.observe.tracker import Det, TrackEnd, Tracker, TrackerConfig

# Labels a detector writes for "nothing here" (a line that keeps the pair in the ledger).
NO_DETECTION = "none"


def tracker_config(cfg: ObserveConfig) -> TrackerConfig:
    """The tracker's thresholds from the `observe` config section."""
    return TrackerConfig(high=cfg.high, low=cfg.low, iou_gate=cfg.iou_gate,
                         min_hits=cfg.min_hits, max_gap_s=cfg.max_gap_s)


def track_record(end: TrackEnd) -> dict[str, Any]:
    """A finished track as one tracks.jsonl object (times in UTC seconds, 3 decimals)."""
    out: dict[str, Any] = msgspec.to_builtins(end)
    for key in ("first_s", "last_s", "label_share", "best_confidence"):
        out[key] = round(out[key], 3)
    out["duration_s"] = round(end.last_s - end.first_s, 3)
    out["best_box"] = [round(v, 1) for v in end.best_box]
    out["path"] = [[round(t, 3), round(x, 1), round(y, 1)] for t, x, y in end.path]
    return {"track": out}


def count_record(counts: IntervalCounts) -> dict[str, Any]:
    """A closed interval as one counts.jsonl object."""
    return {"counts": msgspec.to_builtins(counts)}


@dataclass
class Observations:
    """What one call produced: finished tracks and closed intervals, as JSON objects."""

    tracks: list[dict[str, Any]] = field(default_factory=list)
    counts: list[dict[str, Any]] = field(default_factory=list)


class Observer:
    """Tracks one detector's boxes across pairs by capture time, and counts them."""

    def __init__(self, cfg: ObserveConfig) -> None:
        self.tracker = Tracker(tracker_config(cfg))
        self.counter = Counter(cfg.interval_s)
        self.t_s: float | None = None  # newest capture time fed
        self.late = 0  # results tracked at a newer capture time than their own

    def feed(self, t_wall_ns: int, items: list[dict[str, Any]]) -> Observations:
        """One pair's mono_ir items (dicts with label, confidence, box): each gets `track`,
        its confirmed track's id or None; returns what ended."""
        t_s = t_wall_ns / 1e9
        if self.t_s is not None and t_s < self.t_s:
            self.late += 1
            t_s = self.t_s
        self.t_s = t_s
        boxed = [it for it in items if it.get("label") != NO_DETECTION and len(it["box"]) == 4]
        dets = [Det(label=it["label"], confidence=float(it["confidence"]),
                    box=(it["box"][0], it["box"][1], it["box"][2], it["box"][3]))
                for it in boxed]
        upd = self.tracker.update(t_s, dets)
        for it, tid in zip(boxed, upd.track_ids, strict=True):
            it["track"] = tid
        self.counter.ended(upd.ended)
        closed = self.counter.observe(t_s, upd.seen)
        return Observations([track_record(e) for e in upd.ended],
                            [count_record(c) for c in closed])

    def finish(self) -> Observations:
        """At the end of a run: every track still alive ends, the open interval closes."""
        if self.t_s is None:
            return Observations()
        ended = self.tracker.flush(self.t_s)
        self.counter.ended(ended)
        return Observations([track_record(e) for e in ended],
                            [count_record(c) for c in self.counter.flush(self.t_s)])
