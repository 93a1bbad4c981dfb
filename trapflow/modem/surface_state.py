"""The surface receiver's de-duplication memory on disk, so a restarted `trapflow surface`
still knows which message ids it has written (a retransmission is then not written twice).

One small JSON file, replaced atomically; it also marks how long the output was when it
was saved, so lines written after the last save (never acknowledged) can be cut on load.
"""

from __future__ import annotations

import contextlib
import logging
import os
from pathlib import Path
from typing import Annotated

import msgspec

log = logging.getLogger(__name__)

VERSION = 1

NonNegative = Annotated[int, msgspec.Meta(ge=0)]


class OutputMark(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """Which output file the state belongs to and its size when the state was saved."""

    dev: int
    """st_dev of the output file."""
    ino: int
    """st_ino of the output file."""
    size: NonNegative
    """Bytes in the output once every id in `seen` was written."""


class SurfaceState(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """De-duplication state: the sender's floor and the ids at or above it already written."""

    version: Annotated[int, msgspec.Meta(ge=VERSION, le=VERSION)] = VERSION
    """Format version of the file."""
    floor: NonNegative = 0
    """Every message id below it is settled at the sender."""
    seen: list[NonNegative] = msgspec.field(default_factory=list)
    """Ids >= floor already written to the output (sorted)."""
    output: OutputMark | None = None
    """The output file when it is a regular file, else None."""


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
        state = msgspec.json.decode(data, type=SurfaceState)
    except msgspec.DecodeError as exc:  # ValidationError is a subclass
        log.warning(
            "surface state file %s is corrupt (%s): starting with no memory of written "
            "messages, so a retransmission may be written twice",
            path,
            exc,
        )
        return SurfaceState()
    state.seen = sorted({i for i in state.seen if i >= state.floor})
    return state


def save_state(path: Path, state: SurfaceState) -> None:
    """Write state to path atomically and durably (tmp file, fsync, replace, fsync dir)."""
    tmp = path.with_name(path.name + ".tmp")
    data = msgspec.json.encode(state) + b"\n"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view) :]
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    # The rename itself is durable only once the directory is synced; some filesystems refuse.
    with contextlib.suppress(OSError):
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
