"""The subscriptions a bound tap (XPUB, xpub_manual) takes, and when its process trims the
heap libzmq held for refused ones."""

from __future__ import annotations

from collections.abc import Sequence

import zmq

TAP_RCVHWM = 64  # subscription messages queued from one peer before libzmq stops reading it
# After subscriptions were refused, the process trims its heap this often for this long: the
# memory libzmq held for them is freed when their sender leaves (TapGate.trim_due).
TRIM_INTERVAL_S = 5.0
TRIM_FOR_S = 60.0


class TapGate:
    """The subscriptions a bound tap (XPUB, xpub_manual) takes: only prefixes of its topics.

    A subscription that is no prefix of a topic would never match anything, so refusing it
    changes nothing for a reader; counts per prefix say which topics somebody reads. What
    the process keeps is bounded by the prefixes of a few short topics. (libzmq itself still
    records every subscription a connected peer sent, about 600 bytes each, until that peer
    disconnects; who may connect at all is the run directory's permissions' business.)
    """

    def __init__(self, sock: zmq.Socket[bytes], topics: Sequence[bytes]) -> None:
        self.sock = sock
        self.topics = tuple(topics)
        self._valid = {t[:i] for t in self.topics for i in range(len(t) + 1)}
        self.readers: dict[bytes, int] = {}
        self.refused = 0
        self._refused_seen = 0
        self._trim_until = 0.0  # trims are due until then (refused subscriptions came)
        self._next_trim = 0.0

    def drain(self) -> bool:
        """Take the subscription messages waiting (never blocks); True if readers changed."""
        changed = False
        while True:
            try:
                msg = self.sock.recv(zmq.NOBLOCK)
            except zmq.Again:
                return changed
            prefix = msg[1:]
            if msg[:1] not in (b"\x00", b"\x01") or prefix not in self._valid:
                self.refused += 1  # no topic starts so: it could never match
                continue
            if msg[:1] == b"\x01":
                self.sock.setsockopt(zmq.SUBSCRIBE, prefix)  # for the peer that sent it
                self.readers[prefix] = self.readers.get(prefix, 0) + 1
            else:
                self.sock.setsockopt(zmq.UNSUBSCRIBE, prefix)
                left = self.readers.get(prefix, 0) - 1
                if left > 0:
                    self.readers[prefix] = left
                else:
                    self.readers.pop(prefix, None)
            changed = True

    def trim_due(self, now: float) -> bool:
        """Whether the process should release freed memory now (runtime.node.release_memory):
        every TRIM_INTERVAL_S for TRIM_FOR_S after the last refused subscription, so what a
        hostile subscriber made libzmq hold goes back to the system once it leaves."""
        if self.refused != self._refused_seen:
            self._refused_seen = self.refused
            self._trim_until = now + TRIM_FOR_S
        if now < self._trim_until and now >= self._next_trim:
            self._next_trim = now + TRIM_INTERVAL_S
            return True
        return False

    def wanted(self, topic: bytes) -> bool:
        """Somebody reads topic (subscribed to a prefix of it)."""
        return any(topic.startswith(p) for p in self.readers)
