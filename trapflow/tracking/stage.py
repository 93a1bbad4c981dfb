"""The observation stage, pure: mono detections in (as the normalizer made them), track ids
on them, and the finished tracks and closed intervals out as JSON-able objects.

The normalizer runs it in its own process, on results as they arrive: lines are written at
once, never held back. Results of a pool with several workers can arrive slightly out of
capture order; such a result is tracked at the newest capture time seen (its motion
prediction is a few tens of ms off, well inside the IoU gate), not dropped.

Two clocks: every duration (a track's age, gaps and duration, a counting interval's length,
a speed) is measured on the pairs' capture times on a clock that does not step (the
monotonic clock at capture, or a recording's own stamps: `messages.Result.capture_ns`); the
times written (a track's first_s, last_s and path, an interval's start and end, news) are
wall-clock labels: the measured time plus the newest pair's offset between its label and
its measured time, so a track that spans a step of the wall clock is named in the clock
after the step (after an NTP fix, the right one). Before, the tracker ran on the wall clock:
stepped back an hour, most tracks lasted 0.0 s, some never ended, and no interval closed.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import msgspec
import numpy as np

from trapflow.config.schema import ObserveConfig, ReviewConfig
from trapflow.tracking.counts import Counter, IntervalCounts, News, RunNews
from trapflow.tracking.review import Reviewer
from trapflow.tracking.rigpose import RigPoses, ground_positions
from trapflow.tracking.speed import speeds
from trapflow.tracking.tracker import Det, TrackEnd, Tracker, TrackerConfig

# Labels a detector writes for "nothing here" (a line that keeps the pair in the ledger).
NO_DETECTION = "none"


def tracker_config(cfg: ObserveConfig) -> TrackerConfig:
    """The tracker's thresholds from the `observe` config section."""
    return TrackerConfig(high=cfg.high, low=cfg.low, iou_gate=cfg.iou_gate,
                         dist_gate=cfg.dist_gate, dup_iou=cfg.dup_iou,
                         min_hits=cfg.min_hits, max_gap_s=cfg.max_gap_s,
                         max_boxes=cfg.max_boxes)


# Fewest measured views for a track's speed (a line through fewer is mostly noise).
MIN_SPEED_VIEWS = 4


@dataclass(frozen=True)
class View:
    """One stereo measurement of a tracked animal."""

    t_s: float  # its pair's capture time
    xyz: tuple[float, float, float]
    length_m: float | None
    length_sd_m: float | None


def aggregate(views: list[View], poses: RigPoses | None = None) -> dict[str, Any]:
    """A track's measurements: its length (median of the sharpest half of its views, their
    spread, how many), range and Camtrap DP position at first sighting, and its speed along
    its 3-D path (and over its net displacement, tracking/speed.py).

    With VO's poses (`poses` not empty) the positions are taken in VO's world frame, so the
    rig's own motion is removed (`speed_frame` "ground"); a track none of whose views has a
    pose then gets no speed rather than one against the moving rig. Without VO the rig is
    taken to stand still (`speed_frame` "camera")."""
    if not views:
        return {}
    first = views[0]
    x, y, z = first.xyz
    out: dict[str, Any] = {
        "range_m": round(math.sqrt(x * x + y * y + z * z), 3),
        # Camtrap DP: distance and angle from the camera's axis at first sighting (degrees,
        # positive to the right of the axis).
        "position_radius_m": round(math.hypot(x, z), 3),
        "position_angle_deg": round(math.degrees(math.atan2(x, z)), 1),
    }
    lengths = sorted((v.length_sd_m or 0.0, v.length_m) for v in views if v.length_m)
    if lengths:
        best = [length for _, length in lengths[: max(1, (len(lengths) + 1) // 2)]]
        out["length_m"] = round(float(np.median(best)), 3)
        out["length_spread_m"] = round(float(np.std(best)), 3)
        out["length_views"] = len(best)
    out.update(_speed(views, poses))
    return out


def _speed(views: list[View], poses: RigPoses | None) -> dict[str, Any]:
    """A track's speeds (tracking/speed.py: along its path, its sd, over its net
    displacement) and speed_frame, or nothing (too few views or poses)."""
    times = [v.t_s for v in views]
    if poses:
        got = ground_positions(times, [v.xyz for v in views], poses)
        if got is None:
            return {}
        t, pos, frame = got[0], got[1], "ground"
    else:
        t, pos, frame = np.array(times), np.array([v.xyz for v in views]), "camera"
    if len(t) < MIN_SPEED_VIEWS or t[-1] <= t[0]:
        return {}
    return {**speeds(np.asarray(t), np.asarray(pos)), "speed_frame": frame}


def track_record(end: TrackEnd, views: list[View] | None = None,
                 poses: RigPoses | None = None, label_offset_s: float = 0.0) -> dict[str, Any]:
    """A finished track as one tracks.jsonl object (times in UTC seconds, 3 decimals): the
    tracker's measured times plus `label_offset_s` (the wall clock's lead on them)."""
    out: dict[str, Any] = msgspec.to_builtins(end)
    out["first_s"] = end.first_s + label_offset_s
    out["last_s"] = end.last_s + label_offset_s
    for key in ("first_s", "last_s", "label_share", "best_confidence"):
        out[key] = round(out[key], 3)
    out["duration_s"] = round(end.last_s - end.first_s, 3)
    out["best_box"] = [round(v, 1) for v in end.best_box]
    out["path"] = [[round(t + label_offset_s, 3), round(x, 1), round(y, 1)]
                   for t, x, y in end.path]
    out.update(aggregate(views or [], poses))
    return {"track": out}


def count_record(counts: IntervalCounts) -> dict[str, Any]:
    """A closed interval as one counts.jsonl object."""
    out: dict[str, Any] = msgspec.to_builtins(counts)
    out["start_s"], out["end_s"] = round(counts.start_s, 3), round(counts.end_s, 3)
    for label in out["labels"]:
        label["dwell_s"] = round(label["dwell_s"], 3)
    return {"counts": out}


def _utc(t_s: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(t_s))


def modem_track(record: dict[str, Any]) -> dict[str, Any]:
    """A finished track as the modem carries it (modem/codec.py kind 7): no path, no box,
    no pair count (the interval's counts say the effort), whole seconds, and `measured` =
    [length_m to the cm, range_m to the dm, speed_m_s to the cm/s] where known; the
    surface writes it back as a JSON line."""
    t = record["track"]
    out: dict[str, Any] = {"id": t["id"], "label": t["label"], "start": _utc(t["first_s"]),
                           "duration_s": round(t["last_s"] - t["first_s"]),
                           "confidence": round(t["best_confidence"], 2)}
    measured = [t.get("length_m"), t.get("range_m"), t.get("speed_m_s")]
    if any(m is not None for m in measured):
        out["measured"] = [None if m is None else round(m, nd)
                           for m, nd in zip(measured, (2, 1, 2), strict=True)]
    return {"track": out}


def modem_counts(record: dict[str, Any]) -> dict[str, Any]:
    """A closed interval as the modem carries it (kind 8): start, minutes, per label."""
    c = record["counts"]
    return {"counts": {"start": _utc(c["start_s"]),
                       "minutes": round((c["end_s"] - c["start_s"]) / 60),
                       "pairs": c["pairs"], "labels": c["labels"]}}


def modem_news(news: RunNews) -> list[dict[str, Any]]:
    """The run's news as the modem carries it: `new_label` (kind 9: label, the capture time
    it was seen at, the first track's id) and `new_max_n` (kind 10: label, time, the run's
    new MaxN when above 1)."""
    out: list[dict[str, Any]] = []
    if news.new_label:
        out.append({"new_label": {"label": news.label, "time": _utc(news.t_s),
                                  "track": news.track}})
    if news.max_n > 1:
        out.append({"new_max_n": {"label": news.label, "time": _utc(news.t_s),
                                  "max_n": news.max_n}})
    return out


@dataclass
class Observations:
    """What one call produced: finished tracks and closed intervals, as JSON objects, and
    the run's news (modem records only: the same facts are in the files)."""

    tracks: list[dict[str, Any]] = field(default_factory=list)
    counts: list[dict[str, Any]] = field(default_factory=list)
    news: list[dict[str, Any]] = field(default_factory=list)
    # Tracks queued for review (tracking/review.py): {"review": {...}}, the best view's
    # crop under "jpeg" (bytes) when one was kept.
    reviews: list[dict[str, Any]] = field(default_factory=list)

    def for_modem(self) -> list[dict[str, Any]]:
        """The same, compact, for the outbox; news first."""
        return [*self.news, *map(modem_counts, self.counts), *map(modem_track, self.tracks)]


def track_pairs(pairs: Iterable[tuple[int, list[dict[str, Any]]]],
                cfg: ObserveConfig, poses: RigPoses | None = None) -> Observations:
    """Re-analysis: one input's detection lines, pair by pair in capture order as
    (capture time ns, that pair's mono_ir items), tracked as the live normalizer tracks
    them (their `track` keys set in place), VO's poses (`poses`) taken out of their
    speeds; returns every track and count."""
    obs = Observer(cfg, poses)
    out = Observations()
    for got in [*(obs.feed(t_ns, items) for t_ns, items in pairs), obs.finish()]:
        out.tracks += got.tracks
        out.counts += got.counts
    return out


class Observer:
    """Tracks one detector's boxes across pairs by capture time, and counts them."""

    def __init__(self, cfg: ObserveConfig, poses: RigPoses | None = None,
                 review: ReviewConfig | None = None, pool: str = "") -> None:
        # Which finished tracks to queue for review, and each live track's best view.
        self.reviewer = Reviewer(review, pool) if review is not None and review.enabled else None
        self.tracker = Tracker(tracker_config(cfg))
        self.poses = poses  # the rig's motion from VO, shared by every detector's observer
        self.counter = Counter(cfg.interval_s)
        self.news = News()
        self.views: dict[int, list[View]] = {}  # stereo measurements of live tracks
        self.t_s: float | None = None  # newest capture time fed (measured, plus `shift_s`)
        self.label_offset_s = 0.0  # the newest pair's label minus its measured time
        self.shift_s = 0.0  # added to measured times (a restore on a clock that restarted)
        self.late = 0  # results tracked at a newer capture time than their own
        self.capped = 0  # boxes left out of tracking: more than max_boxes in their pair
        self.resumed = False  # restored from a checkpoint, not fed since

    def __getstate__(self) -> dict[str, Any]:
        """What a checkpoint keeps (normalizer/checkpoint.py): all but the shared poses."""
        return {**self.__dict__, "poses": None}

    def resume(self) -> None:
        """Restored after a cut: the next pair's clock may have restarted (a reboot)."""
        self.resumed = True

    def _resume_clock(self, own_s: float, label_ns: int | None) -> None:
        """The first pair after a restore: on a monotonic clock that restarted (a reboot),
        go on from the newest time restored plus the wall clock's time off (none when it
        went back), so tracks end or continue as the time off says; the same clock (a
        process killed and restarted) needs nothing."""
        self.resumed = False
        if self.t_s is None or own_s + self.shift_s >= self.t_s:
            return
        off = 0.0 if label_ns is None else max(
            0.0, label_ns / 1e9 - (self.t_s + self.label_offset_s))
        self.shift_s = self.t_s + off - own_s

    def feed(self, t_ns: int, items: list[dict[str, Any]],
             label_ns: int | None = None) -> Observations:
        """One pair's mono_ir items (dicts with label, confidence, box) at capture time
        `t_ns` (measured: Result.capture_ns) labelled `label_ns` (its wall clock; t_ns when
        None): each gets `track`, its confirmed track's id or None; returns what ended."""
        own_s = t_ns / 1e9
        if self.resumed:
            self._resume_clock(own_s, label_ns)
        t_s = own_s + self.shift_s
        if self.t_s is not None and t_s < self.t_s:
            self.late += 1
            t_s = self.t_s
        self.t_s = t_s
        label_s = t_s if label_ns is None else label_ns / 1e9 - (own_s + self.shift_s - t_s)
        self.label_offset_s = label_s - t_s
        boxed = [it for it in items if it.get("label") != NO_DETECTION and len(it["box"]) == 4]
        dets = [Det(label=it["label"], confidence=float(it["confidence"]),
                    box=(it["box"][0], it["box"][1], it["box"][2], it["box"][3]))
                for it in boxed]
        upd = self.tracker.update(t_s, dets)
        self.capped += upd.capped
        for it, tid in zip(boxed, upd.track_ids, strict=True):
            it["track"] = tid
            if "v" in it:  # the shape's version stays the line's last key
                it["v"] = it.pop("v")
            if tid is not None and "xyz" in it:
                self.views.setdefault(tid, []).append(View(  # positions at their own time
                    own_s, tuple(it["xyz"]), it.get("length_m"), it.get("length_sd_m")))
        # Counts and news wait for a track's end: only then is its label its record's.
        closed = self.counter.ended(upd.ended) + self.counter.observe(t_s, upd.seen, label_s)
        news = self.news.ended(upd.ended)
        self.news.observe(label_s, upd.seen)
        tracks = self._records(upd.ended)
        return Observations(tracks, [count_record(c) for c in closed],
                            [rec for n in news for rec in modem_news(n)], self._review(tracks))

    def _records(self, ended: tuple[TrackEnd, ...]) -> list[dict[str, Any]]:
        return [track_record(e, self.views.pop(e.id, None), self.poses, self.label_offset_s)
                for e in ended]

    def _review(self, tracks: list[dict[str, Any]]) -> list[dict[str, Any]]:
        """The finished tracks queued for review (a checkpoint from before the review
        queue has no reviewer: none)."""
        reviewer: Reviewer | None = getattr(self, "reviewer", None)
        if reviewer is None:
            return []
        return [line for t in tracks if (line := reviewer.ended(t)) is not None]

    def finish(self) -> Observations:
        """At the end of a run: every track still alive ends, the open interval closes."""
        if self.t_s is None:
            return Observations()
        ended = self.tracker.flush(self.t_s)
        closed = self.counter.ended(ended) + self.counter.flush(self.t_s)
        tracks = self._records(ended)
        return Observations(tracks, [count_record(c) for c in closed],
                            [rec for n in self.news.ended(ended) for rec in modem_news(n)],
                            self._review(tracks))
