"""The modem sender's scheduling, pure: which frame leaves next on the link, or why none does.
No port, no outbox, no clock: callers pass `now` (monotonic seconds) and `wall_ns` (the wall
clock the hourly byte budget is counted in, as the outbox records what was sent).

The rules, one per branch of `Schedule.next`, in order: nothing while the previous frame is
still on the air (the bit rate); a queued REPLY above every class and outside the window (it
gets no acknowledgement), but a repeated one (an answer a replayed frame can ask for again)
only within REPEAT_SHARE of the hourly budget and REPEAT_AIRTIME_SHARE of the air time,
dropped beyond either so data keeps the rest; any reply within REPLY_AIRTIME_SHARE of the
air time while a DATA frame is ready, which goes first beyond it (budget or not, replies
cannot fill the link); data and repeats short of REPLY_RESERVE of the hourly budget, which
only the replies to new commands may use; at most `window` DATA frames waiting for their
ACK; none while a record of a news class (`modem.news`) waits for its ACK, so a lost
frame of news is resent before anything newer reaches the surface; the classes with
records queued and none in flight, by priority rank and then by the oldest head, each
class's records in seq order while they fit the frame; and every frame within the hourly
byte budget. A record's acknowledgement is awaited for the frame's air time, an ACK's, and
the timeout backed off by the record's attempts (`ack_deadline`).

The sender (trapflow.modem.sender) owns the port and the outbox: it writes what this
decides, moves the records in flight, and reports each frame put on the air (`on_air`).
"""

from __future__ import annotations

import collections
from collections.abc import Collection, Iterable, Sequence
from dataclasses import dataclass

from trapflow.config.modem import BITS_PER_BYTE, ModemConfig
from trapflow.modem.frame import (
    DATA,
    OVERHEAD,
    REPLY,
    data_payload,
    frame,
    message_cost,
    put_uvarint,
)
from trapflow.modem.outbox import Stored

HOUR_NS = 3600 * 10**9
ACK_BYTES = 24  # an ACK frame's air time is allowed for in every acknowledgement deadline
IDLE_WAIT_S = 0.1  # longest wait between two steps of the sender

REPEAT_SHARE = 0.1
"""The share of `bytes_per_hour` that repeated replies (cached, lost, stale, wrong session)
may take in any hour: a recorded command frame replayed over and over gets at most this,
and data and the replies to new commands keep the rest (issue 26)."""
REPLY_RESERVE = 0.1
"""The share of `bytes_per_hour` kept for the replies to new commands: data and repeated
replies stop short of it, so a command is answered at once when data has spent the rest
(it waited for the next hour, issue 36 item 5)."""
REPLY_AIRTIME_SHARE = 0.2
"""Budget or not, replies take at most this share of the link's air time while data waits
to go: four recorded command frames replayed once a second took 101 % of a 300 bit/s link
and no data frame got out (issue 36 item 2). Over it, the next DATA frame goes first.
Repeated replies count in it and are held to REPEAT_AIRTIME_SHARE, so the replies to new
commands keep the difference (10 %) however many replayed frames arrive."""
REPEAT_AIRTIME_SHARE = 0.1
"""Budget or not, repeated replies take at most this share of the air time; beyond it one is
dropped (the surface asks again if it still waits)."""
BURST_FRAMES = 1
"""The air-time shares allow a burst of this many largest frames at once (then the share):
one, so that over 90 s of replays at 300 bit/s replies stay under a fifth of the air time
(two let 23 % through)."""

# Why nothing goes out (the sender's `blocked`, in its stats).
BIT_RATE = "bit rate"
WINDOW_FULL = "window full"
BUDGET_SPENT = "hourly byte budget spent"
REPEAT_SHARE_SPENT = "repeated replies' share of the hourly budget or the air time spent"
NEWS_IN_FLIGHT = "news waiting for their acknowledgement"


@dataclass(frozen=True)
class OutReply:
    """A REPLY payload waiting for the link; `repeat`: an answer a replayed frame can ask
    for again (trapflow.modem.command.Reply.repeat)."""

    payload: bytes
    repeat: bool = False


class Queued:
    """A record on its way: encoded body, attempts, ack deadline."""

    __slots__ = ("stored", "body", "attempts", "deadline")

    def __init__(self, stored: Stored, body: bytes) -> None:
        self.stored = stored
        self.body = body
        self.attempts = 0
        self.deadline = 0.0


class ClassQueue:
    """Per-class queue: loaded pending records (oldest first) and the batch in flight."""

    def __init__(self, name: str, rank: int, news: bool = False) -> None:
        self.name = name
        self.rank = rank
        self.news = news  # ModemConfig.is_news: nothing else goes out while it is in flight
        self.queue: collections.deque[Queued] = collections.deque()
        self.cursor = 0  # highest seq loaded from the outbox
        self.inflight: list[Queued] = []


@dataclass(frozen=True)
class Wait:
    """Nothing goes out on this step: `blocked` says why ("": nothing to send), None leaves
    the reason as it was."""

    blocked: str | None


@dataclass(frozen=True)
class SendReply:
    """The first queued REPLY, framed."""

    wire: bytes
    repeat: bool = False


@dataclass(frozen=True)
class DropReply:
    """The first queued REPLY is a repeat over its share of the budget: drop it (the surface
    asks again if it still waits)."""

    why: str


@dataclass(frozen=True)
class SendData:
    """One DATA frame, framed, and the records it carries, each with its class (the heads
    of their classes' queues, in queue order)."""

    wire: bytes
    batch: tuple[tuple[ClassQueue, Queued], ...]


Decision = Wait | SendReply | DropReply | SendData


def floor(last_known: int, classes: Iterable[ClassQueue]) -> int:
    """Lowest seq the surface may still receive as new (everything below is settled)."""
    heads = [last_known + 1]
    for cls in classes:
        heads.extend(m.stored.seq for m in cls.inflight[:1])
        if cls.queue:
            heads.append(cls.queue[0].stored.seq)
    return min(heads)


def ready(classes: Iterable[ClassQueue]) -> list[ClassQueue]:
    """Classes that may send (records queued, none in flight: stop-and-wait per class), by
    priority rank, then the oldest head first."""
    return sorted((c for c in classes if c.queue and not c.inflight),
                  key=lambda c: (c.rank, c.queue[0].stored.seq))


def pack(classes: Iterable[ClassQueue], head_bytes: int, low: int, max_payload: int
         ) -> tuple[list[tuple[ClassQueue, Queued]], int]:
    """The records one DATA payload carries and its size: each class's records in order
    while they fit, then the next class's (a class whose next record does not fit leaves
    room for a smaller one of a later class)."""
    size = head_bytes
    batch: list[tuple[ClassQueue, Queued]] = []
    for cls in classes:
        for msg in cls.queue:
            cost = message_cost(low, msg.stored.seq, msg.body)
            if size + cost > max_payload:
                break
            batch.append((cls, msg))
            size += cost
    return batch, size


class AirShare:
    """A share of the link's air time, as a bucket of air seconds: it fills at `share`
    seconds per second up to `burst_s`; a frame takes its air time out (down to minus the
    larger of the burst and the frame, so one let through while nothing else waited is
    paid back). A frame longer than the burst goes once the bucket is full: were it held
    to its whole air time it would never go (a status reply is longer than one data frame,
    and its retransmissions' answers were all dropped, so one lost reply lost the command).
    Monotonic time only."""

    def __init__(self, share: float, burst_s: float) -> None:
        self.share = share
        self.burst_s = burst_s
        self.credit = burst_s
        self._at: float | None = None

    def _fill(self, now: float) -> None:
        if self._at is not None and now > self._at:
            self.credit = min(self.burst_s, self.credit + (now - self._at) * self.share)
        self._at = now if self._at is None else max(self._at, now)

    def allows(self, airtime: float, now: float) -> bool:
        """Whether a frame of this air time is within the share now."""
        self._fill(now)
        return self.credit >= min(airtime, self.burst_s)

    def spend(self, airtime: float, now: float) -> None:
        self._fill(now)
        self.credit = max(-max(self.burst_s, airtime), self.credit - airtime)


class Schedule:
    """What the link may carry now: the bit rate (when the last frame has left the modem),
    the window, the classes' priorities and the hourly byte budget."""

    def __init__(self, cfg: ModemConfig, session: bytes,
                 sent: Iterable[tuple[int, int]] = ()) -> None:
        self.cfg = cfg  # read at every decision: a changed limit applies at once
        self.session = session
        self.link_free_at = 0.0  # monotonic time the previous frame has left the modem
        # Frames sent in the last hour: (wall ns, bytes), the oldest first.
        self._ledger: collections.deque[tuple[int, int]] = collections.deque(sent)
        self.bytes_last_hour = sum(b for _, b in self._ledger)
        # Of those, the repeated replies (since this start: the outbox records no kind).
        self._repeats: collections.deque[tuple[int, int]] = collections.deque()
        self.repeat_bytes_last_hour = 0
        # Air-time shares of replies and of repeated replies, whatever the budget.
        burst = BURST_FRAMES * self.airtime(cfg.max_frame_payload + OVERHEAD + 16)
        self.reply_air = AirShare(REPLY_AIRTIME_SHARE, burst)
        self.repeat_air = AirShare(REPEAT_AIRTIME_SHARE, burst)

    def next(self, now: float, wall_ns: int, replies: Sequence[OutReply], frames_in_flight: int,
             classes: Collection[ClassQueue], last_known: int) -> Decision:
        """What to send now, or why nothing (`last_known`: the outbox's last seq seen)."""
        if now < self.link_free_at:
            return Wait(BIT_RATE)
        data = self._data(wall_ns, frames_in_flight, classes, last_known)
        if replies:  # above every class; no acknowledgement, so outside the window
            reply = replies[0]
            wire = frame(REPLY, reply.payload)
            airtime = self.airtime(len(wire))
            if reply.repeat and not (self._repeat_fits(len(wire), wall_ns)
                                     and self.repeat_air.allows(airtime, now)):
                return DropReply(REPEAT_SHARE_SPENT)
            if isinstance(data, SendData) and not self.reply_air.allows(airtime, now):
                return data  # replies had their share of the air time: data goes first
            # A new command's reply may use the reserve; a repeat stops short of it, as data.
            if not self._fits(len(wire), wall_ns, reserve=not reply.repeat):
                return DropReply(BUDGET_SPENT) if reply.repeat else Wait(BUDGET_SPENT)
            return SendReply(wire, reply.repeat)
        return data

    def _data(self, wall_ns: int, frames_in_flight: int, classes: Collection[ClassQueue],
              last_known: int) -> Wait | SendData:
        """The next DATA frame, or why none goes."""
        if frames_in_flight >= self.cfg.window:
            return Wait(WINDOW_FULL)
        if any(c.news and c.inflight for c in classes):
            return Wait(NEWS_IN_FLIGHT)
        order = ready(classes)
        if not order:
            return Wait("")
        low = floor(last_known, classes)
        head = bytearray(self.session)
        put_uvarint(head, low)
        batch, size = pack(order, len(head), low, self.cfg.max_frame_payload)
        if not batch:
            return Wait(None)
        if not self._fits(size + OVERHEAD, wall_ns):
            return Wait(BUDGET_SPENT)
        payload = data_payload(self.session, low, ((m.stored.seq, m.body) for _, m in batch))
        return SendData(frame(DATA, payload), tuple(batch))

    def airtime(self, nbytes: int) -> float:
        """Seconds a frame of nbytes takes on the link."""
        return nbytes * BITS_PER_BYTE / self.cfg.bit_rate

    def _fits(self, nbytes: int, wall_ns: int, reserve: bool = False) -> bool:
        """Whether `nbytes` more stay within the hourly budget (frames older than an hour
        leave the count): all of it for a new command's reply (`reserve`), else short of
        REPLY_RESERVE."""
        while self._ledger and self._ledger[0][0] < wall_ns - HOUR_NS:
            self.bytes_last_hour -= self._ledger.popleft()[1]
        budget = self.cfg.bytes_per_hour
        limit = budget if reserve else budget * (1.0 - REPLY_RESERVE)
        return not budget or self.bytes_last_hour + nbytes <= limit

    def _repeat_fits(self, nbytes: int, wall_ns: int) -> bool:
        """Whether a repeated reply of `nbytes` stays within REPEAT_SHARE of the budget."""
        while self._repeats and self._repeats[0][0] < wall_ns - HOUR_NS:
            self.repeat_bytes_last_hour -= self._repeats.popleft()[1]
        budget = self.cfg.bytes_per_hour
        return not budget or self.repeat_bytes_last_hour + nbytes <= budget * REPEAT_SHARE

    def on_air(self, nbytes: int, now: float, wall_ns: int, repeat: bool = False,
               reply: bool = False) -> None:
        """A frame of `nbytes` was written: the link is busy for its air time, and it counts
        in the hourly budget (and in the repeats' share when `repeat`), and a `reply` in
        the replies' share of the air time."""
        airtime = self.airtime(nbytes)
        self.link_free_at = max(now, self.link_free_at) + airtime
        self._ledger.append((wall_ns, nbytes))
        self.bytes_last_hour += nbytes
        if reply or repeat:
            self.reply_air.spend(airtime, now)
        if repeat:
            self._repeats.append((wall_ns, nbytes))
            self.repeat_bytes_last_hour += nbytes
            self.repeat_air.spend(airtime, now)

    def ack_deadline(self, attempts: int) -> float:
        """When a record sent in the frame just put on the air, after `attempts` earlier
        sends, is given up waiting for (its timeout backs off per attempt, capped)."""
        ack_airtime = ACK_BYTES * BITS_PER_BYTE / self.cfg.bit_rate
        wait = min(self.cfg.ack_timeout_s * self.cfg.backoff**attempts, self.cfg.backoff_max_s)
        return self.link_free_at + ack_airtime + wait

    def idle_s(self, now: float) -> float:
        """How long the sender may wait after a step that sent nothing: until the link is
        free, at most IDLE_WAIT_S."""
        if self.link_free_at > now:
            return max(0.0, min(IDLE_WAIT_S, self.link_free_at - now))
        return IDLE_WAIT_S
