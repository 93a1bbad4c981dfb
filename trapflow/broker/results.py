"""Results on their way from the broker to the normalizer: waiting for the next batch, or
sent and not yet acknowledged (sent again, first, to a restarted normalizer). Bounded, so
that a pipeline without a listening normalizer cannot grow the broker without limit."""

from __future__ import annotations

import collections
from typing import Any

import msgspec

from trapflow.errors import ProtocolError
from trapflow.runtime.ratelog import RateLimitedLog
from trapflow.wire import frame_msgs, messages
from trapflow.wire.links import Link

RESULTS_BATCH_BYTES = 64 << 10  # results leave in datagrams of about this size, or less
MAX_WAITING_RESULTS = 100_000  # kept while no normalizer listens; beyond, the oldest go


def bounded(result: messages.Result, limit: int) -> tuple[messages.Result, int]:
    """The result with at most `limit` detections, the most confident (ties: the first),
    in the order the plugin gave them, and how many were cut; unchanged (0 cut) when
    within the limit or not a detector's result."""
    body = result.body
    if not isinstance(body, messages.MonoIR) or len(body.detections) <= limit:
        return result, 0
    dets = body.detections
    best = sorted(range(len(dets)), key=lambda i: (-dets[i].confidence, i))[:limit]
    kept = [dets[i] for i in sorted(best)]
    return (msgspec.structs.replace(result, body=msgspec.structs.replace(body, detections=kept)),
            len(dets) - limit)


class ResultsOut:
    """The broker's results queue to its normalizer link."""

    def __init__(self, ratelog: RateLimitedLog) -> None:
        self.ratelog = ratelog
        self.out: list[Any] = []  # results waiting for this pass's batch (or a normalizer)
        # Sent but not yet written: sent again to a restarted normalizer (kill -9, OOM).
        self.unacked: collections.deque[Any] = collections.deque(maxlen=MAX_WAITING_RESULTS)
        self.dropped = 0

    def add(self, frame: Any) -> None:
        self.out.append(frame)

    def waiting(self) -> int:
        return len(self.out) + len(self.unacked)

    def link_lost(self) -> None:
        """What the lost normalizer was sent but never confirmed goes first to its successor."""
        self.out[:0] = self.unacked
        self.unacked.clear()

    def flush(self, link: Link | None) -> None:
        """Results leave in few datagrams: one wake-up of the normalizer per pass, not one
        each. What the normalizer cannot take now (busy, restarting) waits for the next pass.
        Raises LinkClosed when the normalizer's link closed (the caller drops it)."""
        if len(self.out) > MAX_WAITING_RESULTS:
            extra = len(self.out) - MAX_WAITING_RESULTS
            self.dropped += extra
            self.ratelog.warning("results", "no normalizer: dropped %d oldest results", extra)
            del self.out[:extra]
        while self.out and link is not None:
            n, size = 0, 0
            while n < min(len(self.out), frame_msgs.MAX_LINK_FRAMES) and (
                    n == 0 or size + len(self.out[n]) < RESULTS_BATCH_BYTES):
                size += len(self.out[n])
                n += 1
            try:
                if not link.send(self.out[:n]):
                    return
                self.unacked.extend(self.out[:n])
            except ProtocolError as exc:  # one result too big for a datagram
                self.dropped += 1
                self.ratelog.warning("results", "dropped a result: %s", exc)
                n = 1
            del self.out[:n]

    def acked(self, count: int) -> bool:
        """The normalizer wrote count results; False (taking only those sent) if it claims
        more than it was sent and has not yet acknowledged."""
        ok = 0 < count <= len(self.unacked)
        for _ in range(min(max(count, 0), len(self.unacked))):
            self.unacked.popleft()
        return ok
