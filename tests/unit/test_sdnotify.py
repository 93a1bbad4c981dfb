"""sd_notify over a real AF_UNIX datagram socket, as systemd's manager receives it."""

from __future__ import annotations

import os
import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

from trapflow.runtime import sdnotify


@pytest.fixture
def notify_socket(tmp_path: Path) -> Iterator[tuple[socket.socket, str]]:
    path = str(tmp_path / "notify")
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(path)
    s.settimeout(2.0)
    yield s, path
    s.close()


def _recv(s: socket.socket) -> dict[str, str]:
    data = s.recv(4096).decode()
    return dict(line.split("=", 1) for line in data.split("\n"))


def test_ready_watchdog_status_arrive_as_datagrams(notify_socket: tuple[socket.socket, str]
                                                   ) -> None:
    s, path = notify_socket
    n = sdnotify.Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "10000000"})
    assert n.enabled and n.watchdog_s == 5.0
    assert n.ready("running")
    assert _recv(s) == {"READY": "1", "STATUS": "running"}
    assert n.notify(WATCHDOG=1, STATUS="12 s  in 3.0/s\nsecond line")
    assert _recv(s) == {"WATCHDOG": "1", "STATUS": "12 s  in 3.0/s second line"}
    assert n.stopping()
    assert _recv(s) == {"STOPPING": "1"}
    assert n.sent == 3 and n.failed == 0


def test_abstract_namespace_socket() -> None:
    name = f"trapflow-test-{os.getpid()}"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(b"\0" + name.encode())
    s.settimeout(2.0)
    try:
        assert sdnotify.Notifier({"NOTIFY_SOCKET": "@" + name}).watchdog()
        assert _recv(s) == {"WATCHDOG": "1"}
    finally:
        s.close()


def test_without_systemd_nothing_is_sent() -> None:
    n = sdnotify.Notifier({})
    assert not n.enabled
    assert not n.ready() and n.sent == 0 and n.failed == 0


def test_a_vanished_socket_is_counted_not_raised(tmp_path: Path) -> None:
    n = sdnotify.Notifier({"NOTIFY_SOCKET": str(tmp_path / "gone")})
    assert not n.watchdog()
    assert n.failed == 1


def test_status_is_one_short_line() -> None:
    data = sdnotify.format_state(STATUS="x" * 500)
    assert data == b"STATUS=" + b"x" * sdnotify.MAX_STATUS_CHARS


@pytest.mark.parametrize(("env", "pid", "expected"), [
    ({}, 1, 0.0),
    ({"WATCHDOG_USEC": "4000000"}, 1, 2.0),
    ({"WATCHDOG_USEC": "4000000", "WATCHDOG_PID": "1"}, 1, 2.0),
    ({"WATCHDOG_USEC": "4000000", "WATCHDOG_PID": "2"}, 1, 0.0),  # another process's
    ({"WATCHDOG_USEC": "soon"}, 1, 0.0),
    ({"WATCHDOG_USEC": "0"}, 1, 0.0),
    ({"WATCHDOG_USEC": "-5"}, 1, 0.0),
])
def test_watchdog_interval(env: dict[str, str], pid: int, expected: float) -> None:
    assert sdnotify.watchdog_interval_s(env, pid) == expected
