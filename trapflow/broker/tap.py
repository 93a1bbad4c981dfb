"""The broker's tap: the XPUB it publishes pair metadata, images and stats on (once a
second), taking only subscriptions that are prefixes of its topics, so nothing is sent
that no tap reads. Stats are built here from BrokerState's counters.
"""

from __future__ import annotations

import time
from typing import Any

import msgspec
import zmq

from trapflow.broker.remote_state import RemoteWorkers
from trapflow.broker.state import BrokerState
from trapflow.wire import messages, tap_msgs
from trapflow.wire.transport import Poller, TapGate

_NOBLOCK = int(zmq.NOBLOCK)  # a plain int: zmq's enum flags cost a conversion per call


class TapSide:
    """A base of trapflow.broker.node.BrokerNode: the tap socket, its subscriptions and the
    stats. What it uses of the broker is declared here; the broker defines it."""

    tap: zmq.Socket[bytes]
    gate: TapGate
    wanted: dict[bytes, bool]
    poller: Poller
    state: BrokerState
    remotes: RemoteWorkers
    started: float
    malformed: int
    level: str
    level_reason: str
    _last_in: int
    _last_processed: dict[str, int]
    _last_stats: float

    def _on_subscriptions(self) -> None:
        self.poller.touch(self.tap)
        if self.gate.drain():
            self.wanted = {t: self.gate.wanted(t) for t in tap_msgs.TAP_TOPICS}

    def _publish(self, topic: bytes, *frames: Any) -> None:
        self.poller.touch(self.tap)
        try:
            self.tap.send_multipart([topic, *frames], _NOBLOCK, copy=False)
        except zmq.Again:
            pass  # a slow subscriber loses tap messages; the pipeline never waits

    def _publish_stats(self, now: float) -> None:
        dt = now - self._last_stats
        self._last_stats = now
        pools = self.state.pool_stats()
        for name, ps in pools.items():
            prev = self._last_processed.get(name, 0)
            self._last_processed[name] = ps.processed
            pools[name] = msgspec.structs.replace(ps, rate=round((ps.processed - prev) / dt, 2))
        stats = messages.Stats(
            t_wall_ns=time.time_ns(),
            uptime_s=round(now - self.started, 3),
            pairs_in=self.state.pairs_in,
            rate_in=round((self.state.pairs_in - self._last_in) / dt, 2),
            malformed=self.malformed,
            pools=pools,
            remote=self.remotes.stats(dt, self.state.worker_pools()),
            level=self.level,
            level_reason=self.level_reason,
        )
        self._last_in = self.state.pairs_in
        self._publish(tap_msgs.TOPIC_STATS, messages.encode(stats))  # cheap: once a second
