"""A serial port that may vanish: open, read, write, and reopen later with a reason kept.

Both ends of the modem link (the sender in the box, `trapflow surface` on the ship)
use it, so a port that cannot be opened or disappears never raises into their loops.
"""

from __future__ import annotations

import contextlib
import logging
import select
import time
from typing import Any

import serial

log = logging.getLogger(__name__)

STOPPED = "stopped"  # the reason a sender or surface gives close() at a planned stop


class LinkPort:
    """A pyserial port by URL (or an open port object) with reopen on failure."""

    def __init__(
        self, port: str | Any, baudrate: int = 9600, reopen_interval_s: float = 2.0
    ) -> None:
        self.url = port if isinstance(port, str) else getattr(port, "port", "object")
        self._given = None if isinstance(port, str) else port
        self.baudrate = baudrate
        self.reopen_interval_s = reopen_interval_s
        self._port: Any = None
        self.reason = "not opened yet"
        self._next_open = 0.0
        self.opens = 0
        self.failures = 0

    @property
    def is_open(self) -> bool:
        """True while the port is usable."""
        return self._port is not None

    def ensure_open(self, now: float | None = None) -> bool:
        """Open the port if it is closed and a retry is due; True when open."""
        if self._port is not None:
            return True
        now = time.monotonic() if now is None else now
        if now < self._next_open:
            return False
        self._next_open = now + self.reopen_interval_s
        try:
            if self._given is not None:
                port = self._given
            else:
                if not self.url:
                    self.reason = "no port configured"
                    return False
                port = serial.serial_for_url(
                    self.url, baudrate=self.baudrate, timeout=0, write_timeout=5
                )
        except (serial.SerialException, OSError, ValueError) as exc:
            self._fail(f"cannot open {self.url}: {exc}")
            return False
        self._port = port
        self.opens += 1
        self.reason = ""
        log.info("link port %s open", self.url)
        return True

    def _fail(self, reason: str) -> None:
        if reason != self.reason:
            # Closed on purpose at a stop is no problem; anything else is.
            (log.info if reason == STOPPED else log.warning)("link port inactive: %s", reason)
        self.reason = reason
        self.failures += 1

    def close(self, reason: str = "closed") -> None:
        """Close the port (it will be reopened after reopen_interval_s)."""
        if self._port is not None and self._given is None:
            with contextlib.suppress(serial.SerialException, OSError):
                self._port.close()
        self._port = None
        self._next_open = time.monotonic() + self.reopen_interval_s
        self._fail(reason)

    def read(self) -> bytes:
        """Whatever bytes are waiting (never blocks); b'' when none or closed."""
        if self._port is None:
            return b""
        try:
            waiting = self._port.in_waiting
            data = self._port.read(waiting or 1)
            return bytes(data)
        except (serial.SerialException, OSError) as exc:
            self.close(f"{self.url} failed on read: {exc}")
            return b""

    def write(self, data: bytes) -> bool:
        """Send bytes; False (and the port closed) when the port failed."""
        if self._port is None:
            return False
        try:
            self._port.write(data)
            self._port.flush()
            return True
        except (serial.SerialException, OSError) as exc:
            self.close(f"{self.url} failed on write: {exc}")
            return False

    def wait_readable(self, timeout: float) -> None:
        """Block up to timeout for incoming bytes (or just sleep when the port has no fd)."""
        fd = None
        if self._port is not None:
            try:
                fd = self._port.fileno()
            except (AttributeError, OSError, ValueError, serial.SerialException):
                fd = None
        if fd is None:
            time.sleep(min(timeout, 0.02))
            return
        try:
            select.select([fd], [], [], timeout)
        except (OSError, ValueError):
            time.sleep(min(timeout, 0.02))
