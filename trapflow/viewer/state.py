"""What the viewer knows: a pure core fed with decoded tap messages and status replies.

No sockets, no clock of its own (every call is given `now`), so the web page's snapshot
and the Prometheus numbers are tested without a pipeline. The taps feed it; the page
(/api/state) and /metrics read it.
"""

from __future__ import annotations

import contextlib
import datetime as dt
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any

from trapflow.wire import messages
from trapflow.wire.pool_counters import LEDGER_STATES

HISTORY = 120  # chart points kept per pool (one per stats message: two minutes)
RING = 16  # recent previews kept to match a result to the image it was computed on
ANNOTATED = 256  # recent seqs whose detections and tags are kept
TRAJECTORY = 2000  # VO positions kept for the top view
# Capture-to-result latency buckets in seconds (Prometheus histogram upper bounds).
LATENCY_BUCKETS = (0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)


def parse_timestamp(text: str) -> float:
    """Seconds since the epoch of a normalizer timestamp ('2025-07-07 12:52:43.120', UTC)."""
    # fromisoformat is about 6x faster than strptime (every result line is parsed); the
    # shape is checked first, as it also takes dates alone, a 'T' and time zones.
    if len(text) in (19, 23) and text[10:11] == " " and text[19:20] in ("", "."):
        with contextlib.suppress(ValueError):
            return dt.datetime.fromisoformat(text).replace(tzinfo=dt.timezone.utc).timestamp()
    raise ValueError(f"result timestamp: expected 'YYYY-MM-DD HH:MM:SS[.mmm]', "
                     f"got {text[:40]!r}")


@dataclass
class Histogram:
    """Cumulative-ready bucket counts, a sum and a count (Prometheus histogram shape)."""

    bounds: tuple[float, ...] = LATENCY_BUCKETS
    counts: list[int] = field(default_factory=lambda: [0] * (len(LATENCY_BUCKETS) + 1))
    total: float = 0.0
    n: int = 0

    def observe(self, value: float) -> None:
        i = next((k for k, b in enumerate(self.bounds) if value <= b), len(self.bounds))
        self.counts[i] += 1
        self.total += value
        self.n += 1

    def cumulative(self) -> list[tuple[str, int]]:
        """(le, cumulative count) pairs ending with +Inf, as a histogram exposes them."""
        out, run = [], 0
        for b, c in zip((*[repr(x) for x in self.bounds], "+Inf"), self.counts, strict=True):
            run += c
            out.append((b, run))
        return out


@dataclass
class Frame:
    """One stereo pair the page may show: the broker's preview JPEGs, the full frame's size
    (boxes refer to it) and the motion gate's regions in it."""

    seq: int
    width: int
    height: int
    left: bytes
    right: bytes
    t_wall_ns: int
    motion: tuple[tuple[int, int, int, int], ...] = ()


@dataclass
class PoolSeries:
    """Chart points of one pool, one per stats message."""

    t: deque[float] = field(default_factory=lambda: deque(maxlen=HISTORY))
    rate: deque[float] = field(default_factory=lambda: deque(maxlen=HISTORY))
    drops: deque[float] = field(default_factory=lambda: deque(maxlen=HISTORY))  # per second
    latency_ms: deque[float] = field(default_factory=lambda: deque(maxlen=HISTORY))
    workers: deque[int] = field(default_factory=lambda: deque(maxlen=HISTORY))
    gated_now: bool = False  # the motion gate withheld pairs from it in the last interval


# Keys of a detection line the page shows beside its box: the track's id, and what the
# stereo pair measured (or why it could not).
DETECTION_EXTRAS = ("track", "range_m", "range_sd_m", "length_m", "length_sd_m",
                    "length_method", "unmeasured")


class LiveCounts:
    """Visits and MaxN per label in the current counting interval (aligned to multiples of
    `observe.interval_s` in UTC, as counts.jsonl's are), from the track ids on detection
    lines: the live view of what the normalizer writes to counts.jsonl when the interval
    closes. A visit is a track first seen in the interval (a track seen before, in an
    earlier interval, is no new visit); MaxN the most tracks of a label in one pair."""

    KNOWN = 4096  # track ids remembered across intervals
    PAIRS = 64  # recent pairs whose tracks per label are kept (results come out of order)

    def __init__(self, interval_s: float) -> None:
        self.interval_s = interval_s
        self.start_s: float | None = None
        self._known: OrderedDict[int, None] = OrderedDict()
        self._visits: dict[str, int] = {}
        self._max_n: dict[str, int] = {}
        self._pairs: OrderedDict[int, dict[str, set[int]]] = OrderedDict()

    def add(self, t_s: float, seq: int, label: str, track: int) -> None:
        """One detection with its track id, captured at t_s (seconds since the epoch)."""
        start = t_s // self.interval_s * self.interval_s
        if self.start_s is None or start > self.start_s:
            self.start_s = start
            self._visits, self._max_n, self._pairs = {}, {}, OrderedDict()
        elif start < self.start_s:
            return  # a late line of an interval already closed
        if track not in self._known:
            self._known[track] = None
            self._visits[label] = self._visits.get(label, 0) + 1
            while len(self._known) > self.KNOWN:
                self._known.popitem(last=False)
        seen = self._pairs.setdefault(seq, {}).setdefault(label, set())
        seen.add(track)
        self._max_n[label] = max(self._max_n.get(label, 0), len(seen))
        while len(self._pairs) > self.PAIRS:
            self._pairs.popitem(last=False)

    def view(self) -> dict[str, Any]:
        """The current interval: its start, length and per label visits and MaxN."""
        return {"start_s": self.start_s, "interval_s": self.interval_s,
                "labels": [{"label": k, "visits": self._visits.get(k, 0), "max_n": n}
                           for k, n in sorted(self._max_n.items())]}


# Result kind (the key of a result line) -> the default pool that makes it: the pool of a line
# from before lines named their own (`pool`, results.jsonl v3).
KIND_POOL = {"mono_ir": "mono", "stereo_ir": "stereo", "stereo_vo": "vo", "tags": "tags"}


class ViewState:
    """Everything the page and /metrics show, updated by on_* calls."""

    def __init__(self, frame_hz: float = 2.0, interval_s: float = 600.0) -> None:
        self.frame_interval = 1.0 / frame_hz
        self.counts = LiveCounts(interval_s)
        self.stats: messages.Stats | None = None
        self.status: dict[str, Any] | None = None
        self.status_error = ""
        self.series: dict[str, PoolSeries] = {}
        self._last_dropped: dict[str, int] = {}
        self._last_gated: dict[str, int] = {}
        self._last_stats_t = 0.0
        self.ring: OrderedDict[int, Frame] = OrderedDict()
        self.annotations: OrderedDict[int, dict[str, Any]] = OrderedDict()
        self.shown: Frame | None = None
        self._next_frame = 0.0
        self.frames_in = 0
        self.frames_shown = 0
        self.latency: dict[str, Histogram] = {}
        self._latency_window: dict[str, deque[float]] = {}
        self.results_in: dict[str, int] = {}
        self.malformed = 0
        self.trajectory: deque[tuple[float, float]] = deque(maxlen=TRAJECTORY)
        self.vo_ok = 0
        self.vo_total = 0
        self.stereo_label: dict[str, Any] | None = None
        self.events: list[dict[str, Any]] = []

    # --- inputs ------------------------------------------------------------------------

    def on_stats(self, stats: messages.Stats, now: float) -> None:
        """A stats message from the broker's tap: one chart point per pool."""
        dt_s = max(1e-3, now - self._last_stats_t) if self._last_stats_t else 1.0
        self._last_stats_t = now
        self.stats = stats
        for name, p in stats.pools.items():
            s = self.series.setdefault(name, PoolSeries())
            prev = self._last_dropped.get(name, p.dropped)
            self._last_dropped[name] = p.dropped
            s.gated_now = p.gated > self._last_gated.get(name, p.gated)
            self._last_gated[name] = p.gated
            window = self._latency_window.get(name)  # lines name their pool
            if window is None:
                window = self._latency_window.get(self._kind_of(name))
            lat = sorted(window)[len(window) // 2] * 1000 if window else 0.0
            if window is not None:
                window.clear()
            s.t.append(round(stats.uptime_s, 1))
            s.rate.append(p.rate)
            s.drops.append(round(max(0, p.dropped - prev) / dt_s, 2))
            s.latency_ms.append(round(lat, 1))
            s.workers.append(p.workers)

    @staticmethod
    def _kind_of(pool: str) -> str:
        return next((k for k, v in KIND_POOL.items() if v == pool), pool)

    def on_image(self, header: messages.StereoPair, left: bytes, right: bytes) -> None:
        """A preview from the broker's tap: kept in a short ring; older ones are dropped."""
        self.frames_in += 1
        self.ring[header.seq] = Frame(header.seq, header.width, header.height, left, right,
                                      header.t_wall_ns, header.motion_regions)
        while len(self.ring) > RING:
            self.ring.popitem(last=False)

    def on_result(self, kind: str, fields: dict[str, Any], now_wall: float) -> None:
        """One line of the normalizer's tap: counts, latency, annotations, VO path."""
        self.results_in[kind] = self.results_in.get(kind, 0) + 1
        ts = fields.get("timestamp")
        t_s = parse_timestamp(ts) if isinstance(ts, str) else None
        if t_s is not None:
            latency = max(0.0, now_wall - t_s)
            self.latency.setdefault(kind, Histogram()).observe(latency)
            pool = fields.get("pool")  # two pools of one plugin: each its own window
            self._latency_window.setdefault(pool if isinstance(pool, str) else kind,
                                            deque(maxlen=256)).append(latency)
        seq = fields.get("seq")
        if kind == "stereo_vo":
            self._on_vo(fields)
        elif kind == "stereo_ir":
            self.stereo_label = {"seq": seq, "label": fields.get("label"),
                                 "confidence": fields.get("confidence")}
        if not isinstance(seq, int) or kind not in ("mono_ir", "tags"):
            return
        ann = self.annotations.setdefault(seq, {"detections": [], "tags": []})
        self.annotations.move_to_end(seq)
        while len(self.annotations) > ANNOTATED:
            self.annotations.popitem(last=False)
        if kind == "mono_ir" and len(fields.get("box") or ()) == 4:
            ann["detections"].append({"label": fields.get("label"),
                                      "confidence": fields.get("confidence"),
                                      "box": fields["box"],
                                      **{k: fields[k] for k in DETECTION_EXTRAS if k in fields}})
            if t_s is not None and isinstance(fields.get("track"), int):
                self.counts.add(t_s, seq, str(fields.get("label")), fields["track"])
        elif kind == "tags" and fields.get("corners"):
            ann["tags"].append({"id": fields.get("id"), "corners": fields["corners"]})
        ann["done"] = True

    def _on_vo(self, fields: dict[str, Any]) -> None:
        self.vo_total += 1
        if fields.get("ok"):
            self.vo_ok += 1
        pose = fields.get("pose")
        if isinstance(pose, list) and len(pose) == 3 and all(len(r) == 4 for r in pose):
            # Top view: x to the right, z forward (camera-to-world translation column).
            self.trajectory.append((float(pose[0][3]), float(pose[2][3])))

    def on_status(self, reply: dict[str, Any] | None, error: str = "") -> None:
        """The supervisor's status reply (nodes, ledger, ring), or why there was none."""
        if reply is not None and "nodes" in reply:
            self.status = reply
            self.status_error = ""
        else:
            self.status_error = error or str((reply or {}).get("error", "no status"))

    def on_events(self, events: list[dict[str, Any]]) -> None:
        """The newest event folders: name, pairs, thumbnail file (relative to the run)."""
        self.events = events

    def tick(self, now: float) -> bool:
        """Pick the pair the page shows, at most frame_hz times a second: the newest pair
        a detector or tag finder has answered for, else the newest pair. True if changed."""
        if now < self._next_frame or not self.ring:
            return False
        self._next_frame = now + self.frame_interval
        pick = next((seq for seq in reversed(self.ring) if seq in self.annotations), None)
        seq = pick if pick is not None else next(reversed(self.ring))
        if self.shown is not None and self.shown.seq == seq:
            return False
        self.shown = self.ring[seq]
        self.frames_shown += 1
        return True

    # --- outputs -----------------------------------------------------------------------

    def snapshot(self, now: float) -> dict[str, Any]:
        """The page's whole state as JSON-able builtins."""
        shown = self.shown
        frame = None
        if shown is not None:
            ann = self.annotations.get(shown.seq, {})
            frame = {"seq": shown.seq, "width": shown.width, "height": shown.height,
                     "detections": ann.get("detections", []), "tags": ann.get("tags", []),
                     "motion": [list(r) for r in shown.motion]}
        st = self.status or {}
        modem = next((n for n in st.get("nodes", []) if n["name"] == "modem"), None)
        sup = st.get("supervision") or {}
        return {
            "uptime_s": self.stats.uptime_s if self.stats else 0.0,
            "pairs_in": self.stats.pairs_in if self.stats else 0,
            "rate_in": self.stats.rate_in if self.stats else 0.0,
            "frame": frame,
            "frames": {"received": self.frames_in, "shown": self.frames_shown},
            "pools": {
                name: {"t": list(s.t), "rate": list(s.rate), "drops": list(s.drops),
                       "latency_ms": list(s.latency_ms), "workers": list(s.workers),
                       "gated_now": s.gated_now,
                       "last": messages.to_builtins(self.stats.pools[name])
                       if self.stats and name in self.stats.pools else {}}
                for name, s in self.series.items()
            },
            "vo": {"path": [[round(x, 3), round(z, 3)] for x, z in self.trajectory],
                   "ok": self.vo_ok, "total": self.vo_total,
                   "ok_rate": round(self.vo_ok / self.vo_total, 3) if self.vo_total else None},
            "stereo": self.stereo_label,
            "counts": self.counts.view(),
            "nodes": st.get("nodes", []),
            "ledger": st.get("ledger"),
            # The ledger's per-pool states with their labels, in order: the page lists a
            # pool's pairs by this list, so a new counter shows without a change to it.
            "ledger_states": [{"key": key, "label": label} for key, label in LEDGER_STATES],
            "ring": st.get("ring"),
            "status_error": self.status_error,
            "modem": ({"state": modem["state"], "reason": modem["reason"],
                       **{k: modem["counters"].get(k, 0)
                          for k in ("backlog", "in_flight", "bytes_last_hour")}}
                      if modem else None),
            "events": self.events,
            "results": dict(self.results_in),
            "control": control_view(sup),
            **ladder_view(st),
        }


def ladder_view(status: dict[str, Any]) -> dict[str, Any]:
    """The degradation ladder's level, why, and whether an operator forced it, where the
    status has a ladder (supervision.ladder; a top-level level/level_reason also counts);
    None for each where it has none."""
    lad = (status.get("supervision") or {}).get("ladder") or {}
    return {"level": lad.get("level", status.get("level")),
            "level_reason": lad.get("reason", status.get("level_reason")),
            "level_forced": lad.get("forced")}


def control_view(supervision: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Each pool's runtime control state (lifecycle, count, policy, parameters) with its
    last change from the supervision timeline (seconds since start, what changed)."""
    last: dict[str, dict[str, Any]] = {}
    for e in supervision.get("timeline") or ():
        node = str(e.get("node", ""))
        if e.get("kind") == "control" and node.startswith("pool:"):
            last[node[len("pool:"):]] = {"t_s": e.get("t_s"), "change": e.get("reason")}
    return {name: {**p, "last_change": last.get(name)}
            for name, p in (supervision.get("pools") or {}).items()}
