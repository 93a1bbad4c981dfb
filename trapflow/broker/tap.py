"""The broker's tap: the XPUB it publishes pair metadata, images, the viewer's previews
(trapflow.broker.preview decides when) and stats on (once a second), taking only
subscriptions that are prefixes of its topics, so nothing is sent or encoded that no tap
reads. Stats are built here from BrokerState's counters.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import msgspec
import zmq

from trapflow.broker.preview import PreviewClock
from trapflow.broker.remote_state import RemoteWorkers
from trapflow.broker.state import BrokerState
from trapflow.errors import ProtocolError
from trapflow.runtime.node import release_memory
from trapflow.runtime.ratelog import RateLimitedLog
from trapflow.wire import jpeg, messages, tap_msgs
from trapflow.wire.links import Poller
from trapflow.wire.tap_gate import TAP_RCVHWM, TapGate
from trapflow.wire.transport import SocketSpec, open_socket

log = logging.getLogger(__name__)

_NOBLOCK = int(zmq.NOBLOCK)  # a plain int: zmq's enum flags cost a conversion per call


class BrokerTap:
    """The tap socket of a broker, its subscriptions and the stats it publishes; owned by
    trapflow.broker.node.BrokerNode, which reads the rest from the state and roster given."""

    def __init__(self, ctx: zmq.Context[zmq.Socket[bytes]], endpoint: str, poller: Poller,
                 state: BrokerState, roster: RemoteWorkers, started: float,
                 preview: PreviewClock) -> None:
        # XPUB tells us what taps subscribe to, so nothing is published that nobody reads;
        # a small high-water mark: a slow tap loses messages instead of holding the broker.
        # Manual: only prefixes of the tap's topics are taken (TapGate), nothing else is kept.
        self.sock = open_socket(ctx, SocketSpec(zmq.XPUB, endpoint, bind=True, sndhwm=32,
                                                rcvhwm=TAP_RCVHWM, xpub_manual=True))
        self.gate = TapGate(self.sock, tap_msgs.TAP_TOPICS)
        self.wanted: dict[bytes, bool] = {}
        self._poller = poller
        self._state = state
        self._roster = roster
        self._started = started
        self._last_in = 0
        self._last_processed: dict[str, int] = {}
        self._last_stats = started
        self.preview = preview
        self.preview_failed = 0
        self._ratelog = RateLimitedLog(log)
        poller.register(self.sock)

    def on_subscriptions(self) -> None:
        """Read what taps (un)subscribed to."""
        self._poller.touch(self.sock)
        if self.gate.drain():
            self.wanted = {t: self.gate.wanted(t) for t in tap_msgs.TAP_TOPICS}
            self.preview.want(self.wanted[tap_msgs.TOPIC_PREVIEW], time.monotonic())

    def publish(self, topic: bytes, *frames: Any) -> None:
        """Send now, or lose it: a slow subscriber never holds the broker."""
        self._poller.touch(self.sock)
        try:
            self.sock.send_multipart([topic, *frames], _NOBLOCK, copy=False)
        except zmq.Again:
            pass  # a slow subscriber loses tap messages; the pipeline never waits

    def preview_due(self, pool: str | None, now: float) -> bool:
        """A page is open and the pair that arrived (pool None) or was given to pool is the
        preview it is due (trapflow.broker.preview)."""
        clock = self.preview
        return clock.wanted and (clock.on_arrival(now) if pool is None
                                 else clock.on_dispatch(pool, now))

    def publish_preview(self, header: Any, left: Any, right: Any) -> None:
        """The viewer's preview of a pair: its header frame as received and both sides
        (views of the ring or received frames: encoded before this returns)."""
        try:
            pair = messages.decode_pair_header(header)
            lj, rj = jpeg.preview_pair(pair, getattr(left, "buffer", left),
                                       getattr(right, "buffer", right))
        except (ProtocolError, ValueError) as exc:  # the pair itself still goes its way
            self.preview_failed += 1
            self._ratelog.warning("preview", "no preview of a pair: %s", exc)
            return
        self.publish(tap_msgs.TOPIC_PREVIEW, header, lj, rj)

    def stats_due(self, now: float, interval_s: float) -> bool:
        """Whether interval_s passed since the last stats."""
        return now - self._last_stats >= interval_s

    def publish_stats(self, now: float, malformed: int, level: str, level_reason: str,
                      image: messages.ImageHealth | None = None) -> None:
        """The broker's Stats, with rates since the last ones (and capture's latest
        image-health view, as it told it)."""
        dt = now - self._last_stats
        self._last_stats = now
        state = self._state
        pools = state.pool_stats()
        for name, ps in pools.items():
            prev = self._last_processed.get(name, 0)
            self._last_processed[name] = ps.processed
            pools[name] = msgspec.structs.replace(ps, rate=round((ps.processed - prev) / dt, 2))
        stats = messages.Stats(
            t_wall_ns=time.time_ns(),
            uptime_s=round(now - self._started, 3),
            pairs_in=state.pairs_in,
            rate_in=round((state.pairs_in - self._last_in) / dt, 2),
            malformed=malformed,
            pools=pools,
            remote=self._roster.stats(dt, state.worker_pools()),
            level=level,
            level_reason=level_reason,
            image=image,
        )
        self._last_in = state.pairs_in
        self.publish(tap_msgs.TOPIC_STATS, messages.encode(stats))  # cheap: once a second
        if self.gate.trim_due(now):
            release_memory()  # what refused subscribers made libzmq hold, once they leave
