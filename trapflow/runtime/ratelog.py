"""Logging that cannot flood: one line per key per interval, with a count of the rest;
and names that came from the wire, escaped so that they cannot forge or garble a line."""

from __future__ import annotations

import logging
import time

MAX_KEYS = 256  # distinct keys remembered; the stalest are forgotten beyond


class RateLimitedLog:
    """Log a repeated problem at most once per interval per key."""

    def __init__(self, logger: logging.Logger, interval_s: float = 5.0) -> None:
        self._log = logger
        self._interval = interval_s
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def warning(self, key: str, msg: str, *args: object) -> None:
        """Warn now, or count the warning if this key warned less than an interval ago."""
        self.log(logging.WARNING, key, msg, *args)

    def log(self, level: int, key: str, msg: str, *args: object) -> None:
        """Log at level now, or count the line if this key logged less than an interval ago."""
        now = time.monotonic()
        if now - self._last.get(key, -1e9) < self._interval:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return
        if len(self._last) >= MAX_KEYS and key not in self._last:
            self._forget(now)
        n = self._suppressed.pop(key, 0)
        self._last[key] = now
        if n:
            self._log.log(level, msg + " (and %d more since the last report)", *args, n)
        else:
            self._log.log(level, msg, *args)

    def _forget(self, now: float) -> None:
        """Keys come from code, a few from the wire (pool names): never more than MAX_KEYS."""
        for key in [k for k, t in self._last.items() if now - t >= self._interval]:
            del self._last[key]
            self._suppressed.pop(key, None)
        while len(self._last) >= MAX_KEYS:
            key = next(iter(self._last))
            del self._last[key]
            self._suppressed.pop(key, None)

MAX_WIRE_CHARS = 200  # a logged name from the wire is cut to this many characters


def wire(value: str | bytes) -> str:
    """A name that came from the wire, fit for a log line: escaped like repr() (a newline
    or a control byte shows as \\n or \\x1b, never raw), at most MAX_WIRE_CHARS long."""
    text = value.decode("utf-8", "backslashreplace") if isinstance(value, bytes) else value
    cut = text[:MAX_WIRE_CHARS]
    out = repr(cut)[1:-1]
    return out + "..." if len(text) > MAX_WIRE_CHARS else out


# A record logged with extra={CONSOLE_ONCE: True} reaches the console once per distinct
# message (every worker says it; the log file keeps them all).
CONSOLE_ONCE = "console_once"


class ConsoleOnce(logging.Filter):
    """Pass a record marked CONSOLE_ONCE only the first time its message is seen."""

    def __init__(self) -> None:
        super().__init__()
        self._seen: set[str] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        if not getattr(record, CONSOLE_ONCE, False):
            return True
        text = record.getMessage()
        if text in self._seen:
            return False
        if len(self._seen) < MAX_KEYS:
            self._seen.add(text)
        return True
