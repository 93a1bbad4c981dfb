"""Rate-limited logging and the escaping of names that come from the wire (issue 16 item 8)."""

from __future__ import annotations

import logging

import pytest

from trapflow.runtime import ratelog
from trapflow.runtime.ratelog import RateLimitedLog, wire


@pytest.mark.parametrize(("raw", "logged"), [
    ("mono:0:12", "mono:0:12"),
    ("a\nb", "a\\nb"),  # a newline cannot start a forged line
    ("a\r\nERROR forged", "a\\r\\nERROR forged"),
    ("\x1b[2J", "\\x1b[2J"),  # no terminal escapes
    ("tab\there", "tab\\there"),
    ("\u2028sep", "\\u2028sep"),  # a Unicode line separator is a line break to some readers
    ("caf\u00e9", "caf\u00e9"),  # printable text stays readable
    (b"\xff\xfe\n", "\\\\xff\\\\xfe\\n"),  # bytes that are no UTF-8: escaped, never raw
    ("x" * 500, "x" * ratelog.MAX_WIRE_CHARS + "..."),
])
def test_wire_names_are_escaped(raw: str | bytes, logged: str) -> None:
    out = wire(raw)
    assert out == logged
    assert out.isprintable()


def test_one_line_per_key_per_interval_and_the_rest_counted(
        caplog: pytest.LogCaptureFixture) -> None:
    log = RateLimitedLog(logging.getLogger("t"), interval_s=3600)
    with caplog.at_level(logging.INFO, "t"):
        for i in range(10_000):
            log.warning("hb", "bad heartbeat %d", i)
        log.log(logging.INFO, "other", "another key")
    assert [r.getMessage() for r in caplog.records] == ["bad heartbeat 0", "another key"]


def test_suppressed_count_is_reported_with_the_next_line(
        caplog: pytest.LogCaptureFixture) -> None:
    log = RateLimitedLog(logging.getLogger("t"), interval_s=0.0)
    log._interval = 3600
    with caplog.at_level(logging.WARNING, "t"):
        for _ in range(5):
            log.warning("k", "x")
        log._last["k"] = -1e9  # the interval is over
        log.warning("k", "x")
    assert [r.getMessage() for r in caplog.records] == ["x", "x (and 4 more since the last report)"]


def test_keys_are_bounded() -> None:
    """Keys made from wire names (pools) cannot grow the limiter without bound."""
    log = RateLimitedLog(logging.getLogger("t.quiet"), interval_s=3600)
    logging.getLogger("t.quiet").disabled = True
    for i in range(10 * ratelog.MAX_KEYS):
        log.warning(f"k{i}", "x")
    assert len(log._last) <= ratelog.MAX_KEYS
