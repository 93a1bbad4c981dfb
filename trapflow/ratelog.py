"""Logging that cannot flood: one line per key per interval, with a count of the rest;
and names that came from the wire, escaped so that they cannot forge or garble a line."""

from __future__ import annotations

import logging
import time


class RateLimitedLog:
    """Log a repeated problem at most once per interval per key."""

    def __init__(self, logger: logging.Logger, interval_s: float = 5.0) -> None:
        self._log = logger
        self._interval = interval_s
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def warning(self, key: str, msg: str, *args: object) -> None:
        """Warn now, or count the warning if this key warned less than an interval ago."""
        now = time.monotonic()
        if now - self._last.get(key, -1e9) < self._interval:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return
        n = self._suppressed.pop(key, 0)
        self._last[key] = now
        if n:
            self._log.warning(msg + " (and %d more since the last report)", *args, n)
        else:
            self._log.warning(msg, *args)


MAX_WIRE_CHARS = 200  # a logged name from the wire is cut to this many characters


def wire(value: str | bytes) -> str:
    """A name that came from the wire, fit for a log line: escaped like repr() (a newline
    or a control byte shows as \\n or \\x1b, never raw), at most MAX_WIRE_CHARS long."""
    text = value.decode("utf-8", "backslashreplace") if isinstance(value, bytes) else value
    cut = text[:MAX_WIRE_CHARS]
    out = repr(cut)[1:-1]
    return out + "..." if len(text) > MAX_WIRE_CHARS else out
