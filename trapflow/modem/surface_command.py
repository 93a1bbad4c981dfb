"""The surface end of one signed command (`trapflow surface PORT --command '...'`).

Takes the next counter from its file (saved durably before the command is first sent, so
a counter is never used twice), signs the command for the box's outbox session, sends it
again with backoff until a reply with its counter and a good tag arrives, and follows the
box's two corrections once each: another session (a fresh outbox: the command goes again
to the session the box names) and a stale counter (the counter file was lost: it goes
again above the box's last accepted counter). Both corrections are signed by the box.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import msgspec

from trapflow.errors import ConfigError, ProtocolError
from trapflow.modem.command import parse_reply_body, sign, verify, write_durably
from trapflow.modem.frame import (
    COMMAND,
    REPLY,
    REPLY_BUSY,
    REPLY_OK,
    REPLY_SESSION,
    REPLY_STALE,
    REPLY_STATUSES,
    SESSION_BYTES,
    Command,
    command_body,
    frame,
    split_signed,
)

log = logging.getLogger(__name__)

MAX_CORRECTIONS = 3  # session or counter corrections followed before giving up


class SurfaceCounter(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """The surface's counter file: the next counter to use."""

    next: int = 1


def take_counter(path: Path, at_least: int = 1) -> int:
    """The next counter (at least `at_least`), with the one after it saved durably first."""
    try:
        state = msgspec.json.decode(path.read_bytes(), type=SurfaceCounter)
    except FileNotFoundError:
        state = SurfaceCounter()
    except msgspec.DecodeError as exc:
        raise ConfigError(
            f"command counter file {path} is corrupt ({exc}): expected "
            '{"next": N}; remove it (the box tells the next free counter)'
        ) from None
    counter = max(state.next, at_least)
    write_durably(path, msgspec.json.encode(SurfaceCounter(next=counter + 1)) + b"\n")
    return counter


class CommandClient:
    """One command until its reply: call step() in the loop, on_reply() with REPLY payloads."""

    def __init__(
        self,
        key: bytes,
        counter_path: Path,
        session: bytes,
        cmd: Command,
        retry_s: float = 8.0,
        backoff: float = 1.5,
        retry_max_s: float = 60.0,
    ) -> None:
        if len(session) != SESSION_BYTES:
            raise ConfigError(
                f"--session: expected {SESSION_BYTES * 2} hex digits, got {session.hex()!r}"
            )
        self.key = key
        self.counter_path = counter_path
        self.session = session
        self.body = command_body(cmd)
        self.retry_s, self.backoff, self.retry_max_s = retry_s, backoff, retry_max_s
        self.result: tuple[int, dict[str, Any]] | None = None
        self.counts = {
            "sent": 0,
            "bad_replies": 0,
            "forged_replies": 0,
            "other_replies": 0,
            "busy": 0,
            "corrections": 0,
        }
        self._issue(1)

    def _issue(self, at_least: int) -> None:
        self.counter = take_counter(self.counter_path, at_least)
        self.wire = frame(COMMAND, sign(self.key, COMMAND, self.session, self.counter, self.body))
        self._interval = self.retry_s
        self._next_send = 0.0

    @property
    def done(self) -> bool:
        """True once a final reply came."""
        return self.result is not None

    def due(self, now: float) -> bytes | None:
        """The frame to send now (first time or again), or None."""
        if self.done or now < self._next_send:
            return None
        self._next_send = now + self._interval
        self._interval = min(self._interval * self.backoff, self.retry_max_s)
        self.counts["sent"] += 1
        return self.wire

    def on_reply(self, payload: bytes) -> None:
        """A REPLY payload from the link: ours (counter and tag) or ignored."""
        try:
            reply = split_signed(REPLY, payload)
        except ProtocolError:
            self.counts["bad_replies"] += 1
            return
        if not verify(self.key, reply):
            self.counts["forged_replies"] += 1
            log.warning("reply with a bad tag (counter %d) ignored", reply.counter)
            return
        if reply.counter != self.counter or self.done:
            self.counts["other_replies"] += 1
            return
        try:
            status, data = parse_reply_body(reply.body)
        except ProtocolError as exc:
            self.counts["bad_replies"] += 1
            log.warning("reply %d undecodable: %s", reply.counter, exc)
            return
        if status == REPLY_BUSY:
            self.counts["busy"] += 1
            return  # sent again at the next retry
        if status in (REPLY_SESSION, REPLY_STALE) and self.counts["corrections"] < MAX_CORRECTIONS:
            self.counts["corrections"] += 1
            if status == REPLY_SESSION:
                log.info(
                    "the box's outbox session is %s (not %s): sending there",
                    reply.session.hex(),
                    self.session.hex(),
                )
                self.session = reply.session
                self._issue(self.counter + 1)
            else:
                last = int(data.get("last", self.counter))
                log.info("the box accepted counter %d already: sending as %d", last, last + 1)
                self._issue(last + 1)
            return
        self.result = (status, data)

    def outcome(self) -> dict[str, Any]:
        """The reply as JSON-able data: its status (`reply`), counter, session, then its fields."""
        if self.result is None:
            return {"reply": "timeout", "counter": self.counter, "session": self.session.hex()}
        status, data = self.result
        return {
            "reply": REPLY_STATUSES.get(status, str(status)),
            "counter": self.counter,
            "session": self.session.hex(),
            **data,
        }

    @property
    def ok(self) -> bool:
        """True when the command ran and the box said ok."""
        return self.result is not None and self.result[0] == REPLY_OK
