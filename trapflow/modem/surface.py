"""`trapflow surface`: the ship end of the modem link.

Reads frames from a serial port, acknowledges every DATA frame, drops messages it
has already written (retransmissions), decodes the rest and writes JSON lines.
The memory of written ids is kept per outbox session (the id every DATA frame carries):
a frame of a session not heard from before starts that session's memory empty, so a
fresh outbox's records (numbered from 1 again) are written, never taken for
retransmissions. With a state file the memory survives a restart of the surface.
REPLY frames (answers to signed commands, trapflow.modem.surface_command) go to on_reply.
"""

from __future__ import annotations

import contextlib
import logging
import os
import stat
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

import msgspec

from trapflow.config.modem import DEFAULT_LABELS
from trapflow.errors import ProtocolError
from trapflow.modem import thumb
from trapflow.modem.codec import LinkCodec
from trapflow.modem.frame import (
    ACK,
    DATA,
    LEGACY_DATA,
    REPLY,
    Deframer,
    ack_payload,
    frame,
    parse_data,
)
from trapflow.modem.port import LinkPort
from trapflow.modem.surface_state import (
    MAX_SESSIONS,
    OutputMark,
    SessionState,
    SurfaceState,
    load_state,
    save_state,
)
from trapflow.modem.surface_thumb import Thumbnails

log = logging.getLogger(__name__)


class Dedup:
    """One session's memory: its sender's floor and the ids at or above it written."""

    __slots__ = ("floor", "seen")

    def __init__(self, floor: int = 0, seen: set[int] | None = None) -> None:
        self.floor = floor  # every id below it is settled at the sender
        self.seen = set() if seen is None else seen


class SurfaceReceiver:
    """Receive, acknowledge, de-duplicate, decode, write one JSON object per line."""

    def __init__(
        self,
        port: str | Any,
        out: IO[bytes] | None,
        labels: list[str] | tuple[str, ...] = DEFAULT_LABELS,
        baudrate: int = 9600,
        fsync_interval_s: float = 1.0,
        reopen_interval_s: float = 1.0,
        state_path: Path | None = None,
        on_reply: Callable[[bytes], None] | None = None,
        review_dir: Path | None = None,
    ) -> None:
        self.port = LinkPort(port, baudrate, reopen_interval_s)
        self.out = out  # None: DATA is left unacknowledged (for a surface that writes it)
        self.on_reply = on_reply  # REPLY payloads (a command waits for one)
        self.replies = 0
        self.data_ignored = 0
        self.codec = LinkCodec(labels)
        # Thumbnails of the box's review queue become JPEGs here (None: lines only).
        self.thumbs = Thumbnails(review_dir) if review_dir is not None else None
        self.deframer = Deframer()
        self.fsync_interval_s = fsync_interval_s
        self._last_fsync = time.monotonic()
        # Per session id, the one heard from longest ago first.
        self.sessions: dict[bytes, Dedup] = {}
        self.current = b""  # the session of the last DATA frame
        self.new_sessions = 0
        self.legacy_frames = 0
        self.written = 0
        self.duplicates = 0
        self.undecodable = 0
        self.bad_frames = 0
        self.state_path = state_path
        self.state_saves = 0
        self.cut_bytes = 0
        self._unsaved = False  # ids in memory that the state file does not hold yet
        self._save_error = ""
        if state_path is not None:
            self._load(state_path)

    def run(self, stop: threading.Event) -> None:
        """Step until stop is set."""
        try:
            while not stop.is_set():
                self.step()
                self.port.wait_readable(0.1)
        finally:
            self.close()

    def close(self) -> None:
        """Flush and sync the output, close the port."""
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
            if kind == LEGACY_DATA:
                self._legacy()
                continue
            if kind == REPLY:
                self.replies += 1
                if self.on_reply is not None:
                    self.on_reply(payload)
                continue
            if kind == DATA and self.out is None:
                self.data_ignored += 1
                continue
            if kind != DATA:
                self.bad_frames += 1
                continue
            try:
                session, floor, messages = parse_data(payload)
            except ProtocolError:
                self.bad_frames += 1
                continue
            written = self._accept(session, floor, messages)
            new += written
            # Acknowledge only once the lines are written (and, with a state file, the ids
            # saved): an ack means "on the surface", and never again written as new.
            if self._commit(written > 0):
                self.port.write(frame(ACK, ack_payload(session, (i for i, _ in messages))))
        return new

    def _legacy(self) -> None:
        """A DATA frame of link protocol 1: without a session its ids mean nothing here."""
        self.legacy_frames += 1
        if self.legacy_frames == 1:
            log.error(
                "DATA frame of link protocol 1 (no outbox session) on %s: expected protocol 2; "
                "not acknowledged, so the box keeps its records; update trapflow on the box "
                "to this surface's version",
                self.port.url,
            )

    def _commit(self, wrote: bool) -> bool:
        """Flush the output and save the state when new ids came; False if it could not."""
        if self.state_path is None:
            self._flush(sync=False)
            return True
        self._unsaved = self._unsaved or wrote
        if not self._unsaved:
            return True
        try:
            # Output first: a saved state must never name lines a power cut could still lose.
            self._flush(sync=True)
            save_state(self.state_path, self._snapshot())
        except OSError as exc:
            reason = f"cannot save surface state {self.state_path}: {exc}"
            if reason != self._save_error:
                log.error("%s; not acknowledging until it can", reason)
            self._save_error = reason
            return False
        self._unsaved = False
        self._save_error = ""
        self.state_saves += 1
        return True

    def _output_stat(self) -> os.stat_result | None:
        """The output's stat when it is a regular file (a pipe or terminal has no length)."""
        if self.out is None:
            return None
        try:
            st = os.fstat(self.out.fileno())
        except (OSError, ValueError, AttributeError):
            return None
        return st if stat.S_ISREG(st.st_mode) else None

    def _snapshot(self) -> SurfaceState:
        st = self._output_stat()
        mark = None if st is None else OutputMark(dev=st.st_dev, ino=st.st_ino, size=st.st_size)
        sessions = [
            SessionState(id=sid.hex(), floor=d.floor, seen=sorted(d.seen))
            for sid, d in self.sessions.items()
        ]
        return SurfaceState(sessions=sessions, output=mark)

    def _load(self, path: Path) -> None:
        state = load_state(path)
        self.sessions = {bytes.fromhex(s.id): Dedup(s.floor, set(s.seen)) for s in state.sessions}
        if self.sessions:
            self.current = next(reversed(self.sessions))
        st = self._output_stat()
        mark = state.output
        if mark is None or st is None or (st.st_dev, st.st_ino) != (mark.dev, mark.ino):
            return  # another output file (rotated, replaced): nothing of it to reconcile
        if st.st_size > mark.size:
            # Lines written after the last save were never acknowledged: the sender sends
            # them again, and they are written again, so the first copy goes.
            try:
                assert self.out is not None  # a regular file (_output_stat)
                self.out.flush()
                os.ftruncate(self.out.fileno(), mark.size)
            except OSError as exc:
                log.warning("cannot cut unacknowledged lines from the output: %s", exc)
                return
            self.cut_bytes = st.st_size - mark.size
            log.warning(
                "cut %d bytes from the end of the output: written after the last save of %s "
                "and never acknowledged, they come again",
                self.cut_bytes,
                path,
            )
        elif st.st_size < mark.size:
            log.warning(
                "output is %d bytes but %s expected at least %d (truncated by hand?)",
                st.st_size,
                path,
                mark.size,
            )

    def _session(self, session: bytes) -> Dedup:
        """The session's memory, now the most recent; a new one is empty (all ids new)."""
        dedup = self.sessions.pop(session, None)
        if dedup is None:
            dedup = Dedup()
            self.new_sessions += 1
            log.info("outbox session %s: first frame, every message of it is new", session.hex())
            while len(self.sessions) >= MAX_SESSIONS:
                old = next(iter(self.sessions))
                del self.sessions[old]
                log.info("outbox session %s forgotten: %d newer ones", old.hex(), MAX_SESSIONS)
        self.sessions[session] = dedup
        self.current = session
        return dedup

    def _accept(self, session: bytes, floor: int, messages: list[tuple[int, bytes]]) -> int:
        dedup = self._session(session)
        if floor > dedup.floor:
            dedup.floor = floor
            dedup.seen = {i for i in dedup.seen if i >= floor}
        new = 0
        for msg_id, body in messages:
            if msg_id < dedup.floor or msg_id in dedup.seen:
                self.duplicates += 1
                continue
            dedup.seen.add(msg_id)
            try:
                record = self.codec.decode(body)
            except ProtocolError as exc:
                self.undecodable += 1
                log.warning("message %d undecodable: %s", msg_id, exc)
                record = {"undecodable": {"id": msg_id, "hex": body.hex()}}
            if self.thumbs is not None and isinstance(record.get(thumb.RECORD), dict):
                record = {thumb.RECORD: self.thumbs.add(session, record[thumb.RECORD])}
            assert self.out is not None
            self.out.write(msgspec.json.encode(record) + b"\n")
            self.written += 1
            new += 1
        return new

    def _flush(self, sync: bool) -> None:
        if self.out is None:
            return
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
            "session": self.current.hex(),
            "floor": self.sessions[self.current].floor if self.current else 0,
            "sessions": len(self.sessions),
            "new_sessions": self.new_sessions,
            "legacy_frames": self.legacy_frames,
            "state_saves": self.state_saves,
            "cut_bytes": self.cut_bytes,
            "replies": self.replies,
            "data_ignored": self.data_ignored,
            "thumbnails": 0 if self.thumbs is None else self.thumbs.written,
            "link": self.deframer.stats(),
        }
