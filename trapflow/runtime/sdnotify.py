"""systemd's sd_notify protocol: READY, WATCHDOG and STATUS datagrams to $NOTIFY_SOCKET.

A `Type=notify` unit waits for READY=1 before it counts the service started; with
`WatchdogSec` it kills and restarts a service that stops sending WATCHDOG=1. The protocol
is one AF_UNIX datagram of newline-separated KEY=VALUE lines, so this is the whole client:
no-op when the variable is absent (not under systemd), never raising into the supervisor.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping

log = logging.getLogger(__name__)

ENV_SOCKET = "NOTIFY_SOCKET"
ENV_WATCHDOG_USEC = "WATCHDOG_USEC"
ENV_WATCHDOG_PID = "WATCHDOG_PID"
MAX_STATUS_CHARS = 200  # one line in `systemctl status`; longer text is cut


def socket_address(value: str) -> str | bytes:
    """The datagram address of a NOTIFY_SOCKET value ('@name' is the abstract namespace)."""
    if value.startswith("@"):
        return b"\0" + value[1:].encode()
    return value


def watchdog_interval_s(env: Mapping[str, str] | None = None, pid: int | None = None) -> float:
    """How often to send WATCHDOG=1: half systemd's WATCHDOG_USEC, 0 when no watchdog is
    set for this process (absent, malformed, or WATCHDOG_PID names another process)."""
    env = os.environ if env is None else env
    try:
        usec = int(env.get(ENV_WATCHDOG_USEC, "0"))
    except ValueError:
        return 0.0
    owner = env.get(ENV_WATCHDOG_PID)
    if owner and owner != str(os.getpid() if pid is None else pid):
        return 0.0
    return usec / 2e6 if usec > 0 else 0.0


def format_state(**fields: str | int) -> bytes:
    """One notify datagram: KEY=VALUE lines (STATUS text kept to one short line)."""
    lines = []
    for key, value in fields.items():
        text = str(value).replace("\n", " ")
        if key == "STATUS":
            text = text[:MAX_STATUS_CHARS]
        lines.append(f"{key}={text}")
    return "\n".join(lines).encode()


class Notifier:
    """Sends sd_notify datagrams when run under systemd; does nothing otherwise."""

    def __init__(self, env: Mapping[str, str] | None = None) -> None:
        env = os.environ if env is None else env
        value = env.get(ENV_SOCKET, "")
        self.address: str | bytes | None = socket_address(value) if value else None
        self.watchdog_s = watchdog_interval_s(env)
        self.sent = 0
        self.failed = 0

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def notify(self, **fields: str | int) -> bool:
        """Send one datagram; False (logged once per failure) when it could not be sent."""
        if self.address is None:
            return False
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
                s.sendto(format_state(**fields), self.address)
        except OSError as exc:
            self.failed += 1
            log.warning("sd_notify to %r failed: %s; expected systemd's NOTIFY_SOCKET to "
                        "accept datagrams", self.address, exc)
            return False
        self.sent += 1
        return True

    def ready(self, status: str = "") -> bool:
        return self.notify(READY=1, STATUS=status) if status else self.notify(READY=1)

    def watchdog(self) -> bool:
        return self.notify(WATCHDOG=1)

    def status(self, text: str) -> bool:
        return self.notify(STATUS=text)

    def stopping(self) -> bool:
        return self.notify(STOPPING=1)
