"""Files that survive a full disk and a power cut: whole-file state written atomically, a
line log that never keeps half a line, and space put aside for what must be written at
the worst moment.

Regression (issue 33, disk full): on a 20 MB run filesystem the supervisor opened
ledger.json for writing at the stop, could not write it, and left it empty (the run's
ledger was gone); the normalizer crash-looped on "database or disk is full"; the modem
node gave up, so no health record could say why.
"""

from __future__ import annotations

import contextlib
import errno
import os
from pathlib import Path
from typing import IO


def is_disk_full(exc: BaseException) -> bool:
    """True for the errors a full disk (or a quota) raises: ENOSPC, EDQUOT, and SQLite's
    'database or disk is full'."""
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    return type(exc).__name__ == "OperationalError" and "full" in str(exc)


def write_atomically(path: Path, data: bytes, mode: int = 0o640) -> None:
    """Replace `path` with `data` whole or not at all: a temporary file in the same
    directory, fsynced, renamed over it, the directory fsynced. When any step fails (a
    full disk) the temporary file is removed and the previous file stays as it was; the
    error is raised."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, mode)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    with contextlib.suppress(OSError):  # the rename is durable once the directory is
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


def append_whole(fh: IO[bytes], data: bytes) -> bool:
    """Append `data` (whole lines) to an unbuffered file: all of it, or, when the disk is
    full, none of it (a part already written is cut off, so no line is left half written).
    Returns False when the disk was full; other errors are raised."""
    start = fh.tell()
    view = memoryview(data)
    try:
        while view:
            n = fh.write(view)
            if not n:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            view = view[n:]
    except OSError as exc:
        if not is_disk_full(exc):
            raise
        with contextlib.suppress(OSError):
            fh.truncate(start)
            fh.seek(start)
        return False
    return True


class SpaceReserve:
    """Disk space put aside in a file of `size` bytes (written, not sparse), released when
    what it was kept for must be written: ledger.json at the stop, health records when the
    disk is full. Creating it on a disk already full keeps what could be had."""

    def __init__(self, path: Path, size: int) -> None:
        self.path = path
        self.held = 0
        try:
            with open(path, "wb") as fh:
                block = bytes(min(size, 1 << 16))
                while self.held < size:
                    self.held += fh.write(block[: size - self.held])
                fh.flush()
                os.fsync(fh.fileno())
        except OSError as exc:
            if not is_disk_full(exc):
                raise

    def release(self) -> int:
        """Give the space back (idempotent); returns the bytes freed."""
        freed, self.held = self.held, 0
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path)
        return freed
