"""Writes that survive a full disk (issue 33): whole-file state written atomically, line
files that keep no half line, the outbox's reserve on a small partition and SQLite's
"database or disk is full" as a refusal, not a crash. ENOSPC is injected here; the
integration test fills a real small filesystem."""

from __future__ import annotations

import errno
import io
import os
import shutil
import sqlite3
from pathlib import Path
from typing import Any

import pytest

from trapflow.config.modem import OutboxConfig
from trapflow.modem import outbox as outbox_mod
from trapflow.modem.outbox import Outbox, OutboxFull
from trapflow.runtime.files import SpaceReserve, append_whole, is_disk_full, write_atomically

MB = 1 << 20


def _enospc(*_a: Any, **_k: Any) -> int:
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_a_failed_write_leaves_the_previous_file_whole(tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """Regression: ledger.json was opened for writing at the stop and left empty."""
    path = tmp_path / "ledger.json"
    write_atomically(path, b'{"produced": 10}\n')
    monkeypatch.setattr(os, "write", _enospc)
    with pytest.raises(OSError) as got:
        write_atomically(path, b'{"produced": 11}\n')
    assert is_disk_full(got.value)
    assert path.read_bytes() == b'{"produced": 10}\n'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ledger.json"]  # no temporary left


class _FillingFile(io.RawIOBase):
    """A file on a disk with room for `room` more bytes."""

    def __init__(self, room: int) -> None:
        self.data = bytearray(b"earlier line\n")
        self.room = room

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return len(self.data)

    def seek(self, pos: int, whence: int = 0) -> int:
        return len(self.data)

    def truncate(self, size: int | None = None) -> int:
        del self.data[size or 0:]
        return len(self.data)

    def write(self, b: Any) -> int:
        if not self.room:
            _enospc()
        n = min(len(b), self.room)
        self.data += bytes(b[:n])
        self.room -= n
        return n


def test_a_line_file_keeps_no_half_line_when_the_disk_fills() -> None:
    fh = _FillingFile(room=10)
    assert not append_whole(fh, b'{"mono_ir": {"seq": 1}}\n{"mono_ir": {"seq": 2}}\n')  # type: ignore[arg-type]
    assert bytes(fh.data) == b"earlier line\n"
    fh.room = 100
    assert append_whole(fh, b'{"mono_ir": {"seq": 3}}\n')  # type: ignore[arg-type]
    assert bytes(fh.data).endswith(b'{"mono_ir": {"seq": 3}}\n')


def test_a_reserve_frees_its_space(tmp_path: Path) -> None:
    reserve = SpaceReserve(tmp_path / ".reserve", 3 * MB + 5)
    assert (tmp_path / ".reserve").stat().st_size == 3 * MB + 5
    assert reserve.release() == 3 * MB + 5 and reserve.release() == 0
    assert not (tmp_path / ".reserve").exists()


def test_a_small_partition_still_takes_records(tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """Regression: the fixed 64 MB reserve refused every record on a 20 MB partition."""
    usage = shutil.disk_usage(tmp_path)
    small = type(usage)(total=20 * MB, used=5 * MB, free=15 * MB)
    monkeypatch.setattr(outbox_mod.shutil, "disk_usage", lambda _p: small)
    box = Outbox(tmp_path / "outbox.sqlite", OutboxConfig())
    try:
        assert box.min_free_bytes == MB  # 5 % of 20 MB, under the configured 64 MB
        assert box.append({"stereo_vo": {"ok": True}}) == 1
        tight = type(usage)(total=20 * MB, used=19.5 * MB, free=MB // 2)
        monkeypatch.setattr(outbox_mod.shutil, "disk_usage", lambda _p: tight)
        box.quota_alarm = "measure now"
        with pytest.raises(OutboxFull, match="minimum 1048576"):
            box.append({"stereo_vo": {"ok": True}})
    finally:
        box.close()


def test_sqlite_full_is_a_refusal_not_a_crash(tmp_path: Path,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """Regression: the normalizer crash-looped on 'database or disk is full'."""
    box = Outbox(tmp_path / "outbox.sqlite", OutboxConfig())

    def full(*_a: Any) -> list[int]:
        raise sqlite3.OperationalError("database or disk is full")

    monkeypatch.setattr(box, "_insert", full)
    try:
        with pytest.raises(OutboxFull, match="the disk is full"):
            box.append_many([{"stereo_vo": {"ok": True}}] * 3)
        assert box.refused == 3
    finally:
        box.close()
