"""Event capture, the photo trap proper: when a configured result fires, keep the stereo
pairs from pre_s before to post_s after it (pre-roll in a bounded ring) in an event folder,
with the results that triggered it. Overlapping triggers extend one event; a disk quota
and a free-space floor (psutil) delete the oldest events first.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from collections import deque
from pathlib import Path
from typing import Any

import psutil

from trapflow.config.schema import EventsConfig, TriggerRule
from trapflow.wire.messages import StereoPair

log = logging.getLogger(__name__)


def fires(rule: TriggerRule, obj: dict[str, Any]) -> dict[str, Any] | None:
    """The body of a normalized result line if the rule fires on it."""
    body = obj.get(rule.algorithm)
    if not isinstance(body, dict):
        return None
    candidates = body.get("detections") if isinstance(body.get("detections"), list) else [body]
    for c in candidates or []:
        if not isinstance(c, dict) or "label" not in c:
            continue
        label, conf = c.get("label"), c.get("confidence", 1.0)
        if rule.label is not None and label != rule.label:
            continue
        if rule.not_label is not None and label == rule.not_label:
            continue
        if isinstance(conf, (int, float)) and conf >= rule.min_confidence:
            return body
    return None


class _Event:
    def __init__(self, folder: Path, end_ns: int | None) -> None:
        self.folder = folder
        # None: triggered before any pair reached this node (its tap connected late on a
        # loaded machine); the post-roll counts from the first pair that comes.
        self.end_ns = end_ns
        self.seqs: set[int] = set()
        self.results = 0
        (folder / "left").mkdir(parents=True)
        (folder / "right").mkdir()


class EventCapture:
    """Feed it every pair and result from the tap; it writes event folders under out_dir."""

    def __init__(self, cfg: EventsConfig, out_dir: str | Path) -> None:
        self.cfg = cfg
        self.out = Path(out_dir)
        self.out.mkdir(parents=True, exist_ok=True)
        self._ring: deque[tuple[StereoPair, bytes, bytes]] = deque(maxlen=cfg.max_ring_pairs)
        self._event: _Event | None = None
        self._latest_ns = 0
        self.events_written = 0
        self.events_deleted = 0

    def on_pair(self, header: StereoPair, left: bytes, right: bytes) -> None:
        """A pair from the tap: into the ring, and into the open event while it lasts."""
        self._latest_ns = header.t_mono_ns
        self._ring.append((header, bytes(left), bytes(right)))
        ev = self._event
        if ev is None:
            return
        if ev.end_ns is None:
            ev.end_ns = header.t_mono_ns + int(self.cfg.post_s * 1e9)
        if header.t_mono_ns > ev.end_ns:
            self._close()
        else:
            self._write_pair(ev, header, left, right)

    def on_result(self, obj: dict[str, Any]) -> bool:
        """A normalized result; returns True when it started or extended an event."""
        if not self.cfg.enabled:
            return False
        body = next((b for r in self.cfg.triggers if (b := fires(r, obj)) is not None), None)
        if body is None:
            return False
        seq = body.get("seq")
        t = next((h.t_mono_ns for h, _, _ in self._ring if h.seq == seq), self._latest_ns)
        # No pair seen yet: its time is unknown (0 made an event that closed, empty, at the
        # first pair: a run's first event folder held no image).
        end = t + int(self.cfg.post_s * 1e9) if self._ring else None
        ev = self._event
        if ev is None:
            ev = self._open(t, seq, end)
        if end is not None:
            ev.end_ns = end if ev.end_ns is None else max(ev.end_ns, end)
        with open(ev.folder / "results.jsonl", "a", encoding="utf-8") as fh:
            fh.write(json.dumps(obj, separators=(",", ":")) + "\n")
        ev.results += 1
        return True

    def _open(self, t_ns: int, seq: object, end_ns: int | None) -> _Event:
        self._enforce_quota()
        stamp = time.strftime("%Y%m%d-%H%M%S")
        folder = self.out / f"{stamp}-seq{seq if isinstance(seq, int) else 'x'}"
        n = 1
        while folder.exists():
            folder = folder.with_name(f"{folder.name}-{n}")
            n += 1
        ev = _Event(folder, end_ns)
        start = t_ns - int(self.cfg.pre_s * 1e9)
        for header, left, right in self._ring:
            if header.t_mono_ns >= start:
                self._write_pair(ev, header, left, right)
        self._event = ev
        log.info("event %s started", folder.name)
        return ev

    @staticmethod
    def _write_pair(ev: _Event, header: StereoPair, left: bytes, right: bytes) -> None:
        if header.seq in ev.seqs:  # overlapping windows: never write a pair twice
            return
        ev.seqs.add(header.seq)
        name = f"{header.seq:08d}.jpg"
        (ev.folder / "left" / name).write_bytes(left)
        (ev.folder / "right" / name).write_bytes(right)

    def _close(self) -> None:
        ev = self._event
        if ev is None:
            return
        self._event = None
        info = {"pairs": len(ev.seqs), "first_seq": min(ev.seqs, default=-1),
                "last_seq": max(ev.seqs, default=-1), "results": ev.results}
        (ev.folder / "event.json").write_text(json.dumps(info) + "\n", encoding="utf-8")
        self.events_written += 1
        log.info("event %s closed: %d pairs", ev.folder.name, len(ev.seqs))
        self._enforce_quota()

    def close(self) -> None:
        """Finish the open event (end of run)."""
        self._close()

    def _events(self) -> list[Path]:
        folders = (p for p in self.out.iterdir() if p.is_dir())
        return sorted(folders, key=lambda p: (p.stat().st_mtime_ns, p.name))

    def _enforce_quota(self) -> None:
        def size(p: Path) -> int:
            return sum(f.stat().st_size for f in p.rglob("*") if f.is_file())

        events = [p for p in self._events() if self._event is None or p != self._event.folder]
        sizes = {p: size(p) for p in events}
        total = sum(sizes.values())
        for p in events:
            free = psutil.disk_usage(str(self.out)).free
            if total <= self.cfg.quota_bytes and free >= self.cfg.min_free_bytes:
                break
            shutil.rmtree(p, ignore_errors=True)
            total -= sizes[p]
            self.events_deleted += 1
            log.warning("events: deleted oldest event %s to stay within quota", p.name)
