"""`trapflow surface`: the ship end of the modem link.

Reads frames from a serial port, acknowledges every DATA frame, drops messages it
has already written (retransmissions), decodes the rest and writes JSON lines.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from typing import IO, Any

import msgspec

from trapflow.errors import ProtocolError
from trapflow.modem.codec import DEFAULT_LABELS, LinkCodec
from trapflow.modem.frame import ACK, DATA, Deframer, ack_payload, frame, parse_data
from trapflow.modem.port import LinkPort

log = logging.getLogger(__name__)


class SurfaceReceiver:
    """Receive, acknowledge, de-duplicate, decode, write one JSON object per line."""

    def __init__(
        self,
        port: str | Any,
        out: IO[bytes],
        labels: list[str] | tuple[str, ...] = DEFAULT_LABELS,
        baudrate: int = 9600,
        fsync_interval_s: float = 1.0,
        reopen_interval_s: float = 1.0,
    ) -> None:
        self.port = LinkPort(port, baudrate, reopen_interval_s)
        self.out = out
        self.codec = LinkCodec(labels)
        self.deframer = Deframer()
        self.fsync_interval_s = fsync_interval_s
        self._last_fsync = time.monotonic()
        self.floor = 0  # every id below it is settled at the sender
        self.seen: set[int] = set()
        self.written = 0
        self.duplicates = 0
        self.undecodable = 0
        self.bad_frames = 0

    def run(self, stop: threading.Event) -> None:
        """Step until stop is set."""
        try:
            while not stop.is_set():
                self.step()
                self.port.wait_readable(0.1)
        finally:
            self._flush(sync=True)
            self.port.close("stopped")

    def step(self) -> int:
        """Handle whatever bytes are waiting; returns how many new records were written."""
        if not self.port.ensure_open():
            return 0
        data = self.port.read()
        if not data:
            return 0
        new = 0
        for kind, payload in self.deframer.feed(data):
            if kind != DATA:
                self.bad_frames += 1
                continue
            try:
                floor, messages = parse_data(payload)
            except ProtocolError:
                self.bad_frames += 1
                continue
            new += self._accept(floor, messages)
            self._flush(sync=False)
            # Acknowledge only once the lines are written: an ack means "on the surface".
            self.port.write(frame(ACK, ack_payload(i for i, _ in messages)))
        return new

    def _accept(self, floor: int, messages: list[tuple[int, bytes]]) -> int:
        if floor > self.floor:
            self.floor = floor
            self.seen = {i for i in self.seen if i >= floor}
        new = 0
        for msg_id, body in messages:
            if msg_id < self.floor or msg_id in self.seen:
                self.duplicates += 1
                continue
            self.seen.add(msg_id)
            try:
                record = self.codec.decode(body)
            except ProtocolError as exc:
                self.undecodable += 1
                log.warning("message %d undecodable: %s", msg_id, exc)
                record = {"undecodable": {"id": msg_id, "hex": body.hex()}}
            self.out.write(msgspec.json.encode(record) + b"\n")
            self.written += 1
            new += 1
        return new

    def _flush(self, sync: bool) -> None:
        self.out.flush()
        now = time.monotonic()
        if sync or now - self._last_fsync >= self.fsync_interval_s:
            self._last_fsync = now
            # A pipe or terminal has nothing to sync.
            with contextlib.suppress(OSError, ValueError, AttributeError):
                os.fsync(self.out.fileno())

    def stats(self) -> dict[str, Any]:
        """Counters for display and tests."""
        return {
            "state": "active" if self.port.is_open else "inactive",
            "reason": self.port.reason,
            "written": self.written,
            "duplicates": self.duplicates,
            "undecodable": self.undecodable,
            "bad_frames": self.bad_frames,
            "floor": self.floor,
            "link": self.deframer.stats(),
        }
