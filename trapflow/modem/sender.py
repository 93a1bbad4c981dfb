"""The modem sender: outbox -> prioritised, rate-limited, acknowledged frames on a serial link.

Runs as its own process beside the normalizer, sharing the outbox file. Per class it
is stop-and-wait (one batch in flight, resent until acknowledged or expired), so each
class arrives in order; classes interleave by priority up to `window` frames in flight.
What goes out when (priority, window, bit rate, back-off, byte budget) is decided by
trapflow.modem.schedule; this shell reads and writes the port and the outbox.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec

from trapflow.config.modem import ModemConfig, OutboxConfig
from trapflow.errors import ProtocolError, unreachable
from trapflow.modem.codec import LinkCodec
from trapflow.modem.frame import ACK, COMMAND, Deframer, max_body, parse_ack
from trapflow.modem.outbox import ACKED, REJECTED, OutboxQueue, Stored
from trapflow.modem.port import LinkPort
from trapflow.modem.schedule import (
    HOUR_NS,
    ClassQueue,
    DropReply,
    OutReply,
    Queued,
    Schedule,
    SendData,
    SendReply,
    Wait,
    floor,
)
from trapflow.runtime.ratelog import wire

log = logging.getLogger(__name__)

LOAD_PER_CLASS = 64  # pending records of one class held in memory at once
PURGE_INTERVAL_S = 60.0
MAX_COMMANDS = 8  # COMMAND payloads held for the node between two steps; more are dropped
MAX_REPLIES = 4  # REPLY payloads waiting for the link; the oldest goes first when more come
BACKLOG_INTERVAL_S = 5.0
MAX_TOLD = 64  # (reason, kind) pairs of unsendable records logged; more are only counted


# What an aggregate's best record keeps when the whole one does not fit its frame.
CORE_KEYS = ("timestamp", "seq", "label", "confidence", "box", "track", "v")


def _core(record: dict[str, Any]) -> dict[str, Any]:
    """A record with only its CORE_KEYS (a record of another shape unchanged)."""
    (kind, body), = record.items()
    if not isinstance(body, dict):
        return record
    return {kind: {k: body[k] for k in CORE_KEYS if k in body}}


class ModemSender:
    """Sends outbox records over a serial link; call step() in a loop, or run(stop)."""

    def __init__(
        self,
        outbox_path: str | Path,
        port: str | Any,
        cfg: ModemConfig | None = None,
        outbox_cfg: OutboxConfig | None = None,
        health: Callable[[dict[str, Any]], dict[str, Any] | None] | None = None,
    ) -> None:
        self.cfg = cfg or ModemConfig()
        self.queue = OutboxQueue(outbox_path, outbox_cfg or OutboxConfig())
        self.session = self.queue.session
        self.port = LinkPort(port, self.cfg.baudrate, self.cfg.reopen_interval_s)
        self.codec = LinkCodec(self.cfg.labels)
        self.deframer = Deframer()
        self.health = health
        self.classes: dict[str, ClassQueue] = {}
        self.by_id: dict[int, Queued] = {}
        self._frames: dict[int, tuple[float, set[int]]] = {}  # frame no -> (deadline, ids unacked)
        self._frame_no = 0
        self._last_known = 0
        self._next_housekeeping = 0.0
        self._next_purge = 0.0
        self._next_backlog = 0.0
        # The decisions: bit rate, window, priorities, back-off and the hourly byte budget
        # (counting what was sent in the last hour, before a restart too).
        self.schedule = Schedule(self.cfg, self.session,
                                 self.queue.sent_since(self.queue.clock_ns() - HOUR_NS))
        self.counters = collections.Counter[str]()
        self._told: set[tuple[str, str]] = set()  # unsendable records logged, once per kind
        self.blocked = ""
        self._backlog = 0
        self.commands: collections.deque[bytes] = collections.deque()  # in, for the node
        self.replies: collections.deque[OutReply] = collections.deque()  # out, before any DATA
        self._max_body = max_body(self.cfg.max_frame_payload)

    # --- the loop -----------------------------------------------------------------

    def run(self, stop: threading.Event) -> None:
        """Step until stop is set, sleeping on the port between steps."""
        try:
            while not stop.is_set():
                delay = self.step()
                self.port.wait_readable(delay)
        finally:
            self.close()

    def step(self, now: float | None = None) -> float:
        """One pass: acks in, timeouts, housekeeping, at most one frame out.

        Returns how long the caller may wait before the next step.
        """
        now = time.monotonic() if now is None else now
        if not self.port.ensure_open(now):
            self._requeue_all()
            return min(0.2, self.cfg.reopen_interval_s)
        self._receive()
        self._timeouts(now)
        if now >= self._next_housekeeping:
            self._next_housekeeping = now + self.cfg.housekeeping_s
            self._housekeeping(now)
        sent = self._send(now)
        self.queue.tick()
        return 0.0 if sent else self.schedule.idle_s(now)

    def close(self) -> None:
        """Close the port and the outbox connection."""
        self.port.close("stopped")
        self.queue.close()

    # --- acknowledgements and timeouts ---------------------------------------------------

    def _receive(self) -> None:
        data = self.port.read()
        if not data:
            return
        acked: list[int] = []
        for kind, payload in self.deframer.feed(data):
            if kind == COMMAND:
                if len(self.commands) >= MAX_COMMANDS:
                    self.counters["commands_dropped"] += 1
                else:
                    self.commands.append(payload)
                continue
            if kind != ACK:
                self.counters["unexpected_frames"] += 1
                continue
            try:
                session, got = parse_ack(payload)
            except ProtocolError:
                self.counters["bad_acks"] += 1
                continue
            if session != self.session:
                # The ids are another outbox's seqs: settling them would drop our own records.
                self.counters["foreign_acks"] += 1
                continue
            acked.extend(got)
        if not acked:
            return
        # Every acknowledged id is on the surface, even one whose wait already timed out
        # (or one sent before a restart): settle them all, so none is sent again.
        self.queue.resolve(acked, ACKED)
        done = set(acked)
        self.counters["acked"] += len(done)
        for msg_id in done & self.by_id.keys():
            msg = self.by_id.pop(msg_id)
            cls = self.classes.get(msg.stored.cls)
            if cls is not None and msg in cls.inflight:
                cls.inflight.remove(msg)
        for cls in self.classes.values():
            if any(m.stored.seq in done for m in cls.queue):
                cls.queue = collections.deque(m for m in cls.queue if m.stored.seq not in done)
        for no, (_, ids) in list(self._frames.items()):
            ids.difference_update(done)
            if not ids:
                del self._frames[no]

    def _timeouts(self, now: float) -> None:
        self._frames = {no: f for no, f in self._frames.items() if f[0] > now}
        for cls in self.classes.values():
            if cls.inflight and min(m.deadline for m in cls.inflight) <= now:
                self.counters["timeouts"] += 1
                for msg in reversed(cls.inflight):
                    self.by_id.pop(msg.stored.seq, None)
                    cls.queue.appendleft(msg)
                cls.inflight = []

    def _requeue_all(self) -> None:
        for cls in self.classes.values():
            for msg in reversed(cls.inflight):
                self.by_id.pop(msg.stored.seq, None)
                cls.queue.appendleft(msg)
            cls.inflight = []
        self._frames.clear()

    # --- loading, expiry, aggregation ---------------------------------------------------

    def _class(self, name: str) -> ClassQueue:
        cls = self.classes.get(name)
        if cls is None:
            cls = self.classes[name] = ClassQueue(name, self.cfg.priority_of(name),
                                                  self.cfg.is_news(name))
        return cls

    def _load(self, cls: ClassQueue) -> None:
        room = LOAD_PER_CLASS - len(cls.queue) - len(cls.inflight)
        if room <= 0:
            return
        rows = self.queue.pending(cls.name, cls.cursor, room)
        tried = self.queue.tried([s.seq for s in rows])
        for stored in rows:
            cls.cursor = stored.seq
            if stored.seq in self.by_id:
                continue  # in flight already (a reload after aggregation)
            if not stored.intact:
                self._unsendable(stored, "corrupt", stored.cls, "its checksum failed")
                continue
            try:
                record = stored.record()
                body = self.codec.encode(record)
            except (ValueError, msgspec.DecodeError) as exc:
                self._unsendable(stored, "undecodable", stored.cls, str(exc))
                continue
            if len(body) > self._max_body:
                kind = next(iter(record), stored.cls) if len(record) == 1 else stored.cls
                self._unsendable(stored, "too_large", kind, f"{len(body)} bytes encoded, a "
                                 f"frame carries at most {self._max_body}")
                continue
            msg = Queued(stored, body)
            msg.attempts = int(stored.seq in tried)  # sent before a restart: may be up there
            cls.queue.append(msg)

    def _unsendable(self, stored: Stored, reason: str, kind: str, why: str) -> None:
        """A record that can never be sent: settled as rejected, counted by reason, and
        logged the first time a kind of record is refused for it (never in silence)."""
        self.queue.resolve([stored.seq], REJECTED)
        self.counters[reason] += 1
        if (reason, kind) in self._told or len(self._told) >= MAX_TOLD:
            return
        self._told.add((reason, kind))
        log.warning("outbox record %d (%s) cannot be sent: %s; counted as %s (logged once per "
                    "kind of record)", stored.seq, wire(kind), wire(why), reason)

    def _housekeeping(self, now: float) -> None:
        last = self.queue.last_seq()
        if last != self._last_known:
            for name in self.queue.classes(self._last_known):
                self._class(name)
            self._last_known = last
        if now >= self._next_backlog:  # a full count: not on every pass
            self._next_backlog = now + BACKLOG_INTERVAL_S
            self._backlog = self.queue.counts()[2]
        wall = time.time_ns()
        for cls in list(self.classes.values()):
            self._expire(cls, self.queue.clock_ns())
            self._load(cls)
            if self.cfg.aggregates(cls.name) and len(cls.queue) > self.cfg.aggregate_backlog:
                self._aggregate(cls, wall)
        if self.health is not None:
            record = self.health(self.stats())
            if record is not None:
                self.queue.replace(record, "health", [])
        if now >= self._next_purge:
            self._next_purge = now + PURGE_INTERVAL_S
            self.queue.purge()

    def _expire(self, cls: ClassQueue, now_ns: int) -> None:
        """Time-to-live on the outbox's clock (now_ns): no wall-clock step expires a record."""
        ttl = self.cfg.ttl_of(cls.name)
        if ttl <= 0:
            return
        before = now_ns - int(ttl * 1e9)
        gone = self.queue.expire(cls.name, before, keep=[m.stored.seq for m in cls.inflight])
        if gone:
            self.counters["expired"] += gone
            cls.queue = collections.deque(m for m in cls.queue if m.stored.up_ns >= before)

    def _aggregate(self, cls: ClassQueue, wall_ns: int) -> None:
        interval_ns = int(self.cfg.aggregate_interval_s * 1e9)
        current = wall_ns // interval_ns
        buckets: dict[int, list[Queued]] = collections.defaultdict(list)
        for msg in cls.queue:
            bucket = msg.stored.t_ns // interval_ns
            # A record sent once may already be on the surface: summarising it would count it twice.
            fresh = not msg.attempts and not msg.stored.body.startswith(b'{"aggregate"')
            if bucket < current and fresh:
                buckets[bucket].append(msg)
        made = False
        for members in buckets.values():
            if len(members) < 2:
                continue
            record = self._summary(cls.name, [m.stored.record() for m in members])
            self.queue.replace(record, cls.name, [m.stored.seq for m in members])
            self.counters["aggregated"] += len(members)
            self.counters["aggregates"] += 1
            made = True
        if made:
            # Reload from the outbox: the aggregates take their place in seq order.
            cls.queue.clear()
            cls.cursor = 0
            self._load(cls)

    def _summary(self, name: str, records: list[dict[str, Any]]) -> dict[str, Any]:
        bodies = [next(iter(r.values())) for r in records]
        stamps = sorted(b["timestamp"] for b in bodies if isinstance(b.get("timestamp"), str))

        def score(rec: dict[str, Any]) -> float:
            value = next(iter(rec.values())).get("confidence", 0.0)
            return float(value) if isinstance(value, (int, float)) else 0.0

        best = sorted(records, key=score, reverse=True)[: self.cfg.aggregate_best]
        summary: dict[str, Any] = {"class": name}
        if stamps:
            summary["from"], summary["to"] = stamps[0], stamps[-1]
        summary["count"] = len(records)
        summary["best"] = best
        record = {"aggregate": summary}
        # Keep the summary inside one frame: the best records whole if they fit, else as
        # their core (what was seen, when, where, which track: a measured detection alone
        # made an aggregate 81 bytes of the default 80), then the weakest dropped until it fits.
        if len(self.codec.encode(record)) > self._max_body:
            summary["best"] = best = [_core(r) for r in best]
        while best and len(self.codec.encode(record)) > self._max_body:
            best.pop()
        return record

    # --- sending ----------------------------------------------------------------------

    def floor(self) -> int:
        """Lowest seq the surface may still receive as new (everything below is settled)."""
        return floor(self._last_known, self.classes.values())

    def send_reply(self, payload: bytes, repeat: bool = False) -> None:
        """Queue a REPLY payload: it goes out before any DATA, within the bit rate and the
        hourly budget, a `repeat` only within its share of it (the surface sends its command
        again until a reply arrives)."""
        if any(r.payload == payload for r in self.replies):
            return  # the same reply already waits (a retransmitted command)
        if len(self.replies) >= MAX_REPLIES:
            # A repeat goes first: the answer to a new command must not give way to a replay.
            old = next((r for r in self.replies if r.repeat), self.replies[0])
            self.replies.remove(old)
            self.counters["replies_dropped"] += 1
        self.replies.append(OutReply(payload, repeat))

    def take_commands(self) -> list[bytes]:
        """COMMAND payloads received since the last call."""
        out = list(self.commands)
        self.commands.clear()
        return out

    def _send(self, now: float) -> bool:
        """At most one frame out, as the schedule decides; False when none left."""
        wall = self.queue.clock_ns()  # the hourly budget's clock: the outbox's, never stepped
        d = self.schedule.next(now, wall, self.replies, len(self._frames),
                               self.classes.values(), self._last_known)
        if isinstance(d, Wait):
            if d.blocked is not None:
                self.blocked = d.blocked
            return False
        if isinstance(d, DropReply):
            self.replies.popleft()
            self.counters["replies_over_share"] += 1
            return self._send(now)  # at most MAX_REPLIES deep: each call drops one
        if not self.port.write(d.wire):
            self._requeue_all()
            return False
        if isinstance(d, SendReply):
            self.schedule.on_air(len(d.wire), now, wall, d.repeat, reply=True)
            self.replies.popleft()
            self.queue.record_sent(len(d.wire), [], wall)
            self.counters["replies"] += 1
            self.counters["replies_repeated"] += d.repeat
            self.counters["bytes"] += len(d.wire)
        elif isinstance(d, SendData):
            self.schedule.on_air(len(d.wire), now, wall)
            self._in_flight(d, wall)
        else:
            unreachable(d)
        self.blocked = ""
        return True

    def _in_flight(self, d: SendData, wall: int) -> None:
        """A DATA frame left: recorded in the outbox (records sent the first time), its
        records in flight until their acknowledgement deadlines."""
        self.queue.record_sent(len(d.wire), [m.stored.seq for _, m in d.batch if not m.attempts],
                               wall)
        for cls, msg in d.batch:
            cls.queue.popleft()
            msg.deadline = self.schedule.ack_deadline(msg.attempts)
            if msg.attempts:
                self.counters["retransmits"] += 1
            msg.attempts += 1
            cls.inflight.append(msg)
            self.by_id[msg.stored.seq] = msg
        self._frame_no += 1
        self._frames[self._frame_no] = (
            max(m.deadline for _, m in d.batch),
            {m.stored.seq for _, m in d.batch},
        )
        self.counters["frames"] += 1
        self.counters["bytes"] += len(d.wire)
        self.counters["messages"] += len(d.batch)

    # --- stats ------------------------------------------------------------------------

    def stats(self) -> dict[str, Any]:
        """State, reason and counters for the stats topic."""
        return {
            "state": "active" if self.port.is_open else "inactive",
            "reason": self.port.reason,
            "blocked": self.blocked,
            "port": self.port.url,
            "session": self.session.hex(),
            "bytes_last_hour": self.schedule.bytes_last_hour,
            "bytes_per_hour": self.cfg.bytes_per_hour,
            "repeat_bytes_last_hour": self.schedule.repeat_bytes_last_hour,
            "backlog": self._backlog,
            "in_flight": len(self.by_id),
            "queued": {c.name: len(c.queue) for c in self.classes.values() if c.queue},
            "link": self.deframer.stats(),
            **dict(self.counters),
        }
