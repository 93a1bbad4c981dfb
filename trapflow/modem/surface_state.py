"""The surface receiver's de-duplication memory on disk, so a restarted `trapflow surface`
still knows which message ids it has written (a retransmission is then not written twice).

One small JSON file, replaced atomically; it also marks how long the output was when it
was saved, so lines written after the last save (never acknowledged) can be cut on load.
The memory is kept per outbox session (message ids are an outbox's seqs, and a fresh
outbox numbers from 1 again), for the MAX_SESSIONS sessions heard from last. A format 1
file (one memory, no sessions) loads with its output mark and without its ids.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import msgspec

from trapflow.runtime.files import write_atomically

log = logging.getLogger(__name__)

VERSION = 2
MAX_SESSIONS = 32
"""Sessions remembered; one not heard from in this many newer ones is forgotten (its
records, should that outbox ever come back, may then be written twice, never lost)."""

NonNegative = Annotated[int, msgspec.Meta(ge=0)]
SessionHex = Annotated[str, msgspec.Meta(pattern="^[0-9a-f]{8}$")]


class OutputMark(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """Which output file the state belongs to and its size when the state was saved."""

    dev: int
    """st_dev of the output file."""
    ino: int
    """st_ino of the output file."""
    size: NonNegative
    """Bytes in the output once every id in `seen` was written."""


class SessionState(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """One outbox session's de-duplication state: its floor and the ids at or above it
    already written."""

    id: SessionHex
    """The session id, as 8 lowercase hex digits."""
    floor: NonNegative = 0
    """Every message id below it is settled at the sender."""
    seen: list[NonNegative] = msgspec.field(default_factory=list)
    """Ids >= floor already written to the output (sorted)."""


class SurfaceState(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """De-duplication state of every remembered session, and the output mark."""

    version: Annotated[int, msgspec.Meta(ge=VERSION, le=VERSION)] = VERSION
    """Format version of the file."""
    sessions: list[SessionState] = msgspec.field(default_factory=list)
    """Remembered sessions, the one heard from longest ago first."""
    output: OutputMark | None = None
    """The output file when it is a regular file, else None."""


class _StateV1(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """Format 1 (link protocol 1, no sessions): read only to keep its output mark."""

    version: Annotated[int, msgspec.Meta(ge=1, le=1)]
    floor: NonNegative = 0
    seen: list[NonNegative] = msgspec.field(default_factory=list)
    output: OutputMark | None = None


class _Version(msgspec.Struct):
    """Just the format version, to choose the decoder."""

    version: int = VERSION


def load_state(path: Path) -> SurfaceState:
    """The saved state; an empty one (with a warning) when the file is corrupt or unreadable."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return SurfaceState()
    except OSError as exc:
        log.warning(
            "surface state file %s unreadable (%s): starting with no memory of written "
            "messages, so a retransmission may be written twice",
            path,
            exc,
        )
        return SurfaceState()
    try:
        version = msgspec.json.decode(data, type=_Version).version
        if version == 1:
            old = msgspec.json.decode(data, type=_StateV1)
            log.warning(
                "surface state file %s is format 1 (link protocol 1, no outbox sessions): "
                "its %d remembered ids belong to no session, so a record the box sent before "
                "its upgrade and sends again may be written twice; the file is rewritten as "
                "format %d at the next save",
                path,
                len(old.seen),
                VERSION,
            )
            return SurfaceState(output=old.output)
        state = msgspec.json.decode(data, type=SurfaceState)
    except msgspec.DecodeError as exc:  # ValidationError is a subclass
        log.warning(
            "surface state file %s is corrupt (%s; expected format 1 or %d): starting with "
            "no memory of written messages, so a retransmission may be written twice",
            path,
            exc,
            VERSION,
        )
        return SurfaceState()
    latest: dict[str, SessionState] = {}
    for session in state.sessions:  # a repeated id: the later (more recent) entry counts
        latest.pop(session.id, None)
        session.seen = sorted({i for i in session.seen if i >= session.floor})
        latest[session.id] = session
    state.sessions = list(latest.values())[-MAX_SESSIONS:]
    return state


def save_state(path: Path, state: SurfaceState) -> None:
    """Write state to path atomically and durably."""
    write_atomically(path, msgspec.json.encode(state) + b"\n", mode=0o644)
