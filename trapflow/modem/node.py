"""The modem process: sends outbox records to the surface and adds health records.

Owns a SUB of the broker's stats (pool rates and the ladder's level for health: a level
change sends a health record at once). The serial port is opened and re-opened by the
sender; while it is missing the node is inactive with the reason, the outbox keeps filling,
and sending resumes when the port is back.
"""

from __future__ import annotations

import logging
from typing import Any

import zmq

from trapflow import messages
from trapflow.errors import ProtocolError
from trapflow.modem.health import HealthMonitor
from trapflow.modem.sender import ModemSender
from trapflow.node import ACTIVE, FINALIZED, INACTIVE, Node, NodeSpec
from trapflow.transport import SocketSpec, open_socket

log = logging.getLogger(__name__)


class ModemNode(Node):
    """Runs ModemSender.step() between heartbeats."""

    def __init__(self, spec: NodeSpec) -> None:
        super().__init__(spec)
        self.stats_sub = open_socket(self.ctx, SocketSpec(
            zmq.SUB, self.endpoints.tap, subscribe=(messages.TOPIC_STATS,), rcvhwm=4))
        self.pools: dict[str, tuple[float, int]] = {}
        health = None
        if self.cfg.health.enabled or self.cfg.ladder.enabled:  # a level change: a record
            health = HealthMonitor(self.cfg.health, spec.run_dir, lambda: self.pools)
        self.health = health
        self.sender = ModemSender(spec.run_dir / self.cfg.outbox.path, self.cfg.modem.port,
                                  self.cfg.modem, self.cfg.outbox, health)

    def counters(self) -> dict[str, int]:
        return {k: v for k, v in self.sender.stats().items() if isinstance(v, int)}

    def run(self) -> int:
        while not self.stopping:
            delay = self.sender.step()
            st: dict[str, Any] = self.sender.stats()
            if st.get("state") == "active":
                self.set_state(ACTIVE)
            else:
                self.set_state(INACTIVE, str(st.get("reason", "")))
            self._read_stats()
            self.beat()
            self.sender.port.wait_readable(min(delay, 0.1))
        self.sender.close()
        self.set_state(FINALIZED)
        return 0

    def _read_stats(self) -> None:
        while True:
            try:
                _topic, data = self.stats_sub.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return
            except ValueError:
                continue
            try:
                stats = messages.decode_stats(data)
            except ProtocolError:
                continue
            self.pools = {n: (p.rate, p.dropped) for n, p in stats.pools.items()}
            if self.health is not None:
                self.health.set_level(stats.level)
