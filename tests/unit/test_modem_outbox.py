"""Outbox: append, read back, checksums, resolution, retention and quota."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from trapflow.config.modem import OutboxConfig
from trapflow.modem.outbox import (
    ACKED,
    AGGREGATED,
    EXPIRED,
    Outbox,
    OutboxFull,
    OutboxQueue,
    message_class,
)


def crab(seq: int) -> dict[str, object]:
    return {
        "mono_ir": {
            "timestamp": "2025-07-07 12:52:43.120",
            "seq": seq,
            "label": "crab",
            "confidence": 0.71,
            "box": [5.4, 7.8, 15.6, 18.1],
        }
    }


@pytest.mark.parametrize(
    ("record", "expected"),
    [
        (crab(1), "mono_ir/crab"),
        ({"stereo_ir": {"label": "scallop", "confidence": 0.9}}, "stereo_ir/scallop"),
        ({"stereo_vo": {"ok": True}}, "stereo_vo"),
        ({"health": {"uptime_s": 3}}, "health"),
        ({"aggregate": {"class": "mono_ir/crab", "count": 3}}, "mono_ir/crab"),
        ({"a": 1, "b": 2}, "other"),
        ({"mono_ir": {"label": 3}}, "mono_ir"),
    ],
)
def test_message_class(record: dict[str, object], expected: str) -> None:
    assert message_class(record, OutboxConfig().class_fields) == expected


def test_append_read_resolve(tmp_path: Path) -> None:
    path = tmp_path / "outbox.sqlite"
    box = Outbox(path, OutboxConfig(fsync_interval_s=0.05))
    seqs = [box.append(crab(i)) for i in range(5)]
    assert seqs == [1, 2, 3, 4, 5]
    box.sync()
    assert box.durable_seq == 5
    queue = OutboxQueue(path, OutboxConfig())
    assert queue.classes() == ["mono_ir/crab"]
    assert queue.classes(5) == [] and queue.last_seq() == 5
    assert [s.seq for s in queue.pending("mono_ir/crab")] == seqs
    assert queue.pending("mono_ir/crab")[2].record() == crab(2)
    queue.resolve([1, 2], ACKED)
    queue.resolve([2], EXPIRED)  # idempotent: the first resolution stands
    assert [s.seq for s in queue.pending("mono_ir/crab")] == [3, 4, 5]
    assert queue.floor() == 3
    agg = queue.replace(
        {"aggregate": {"class": "mono_ir/crab", "count": 2}}, "mono_ir/crab", [3, 4]
    )
    assert agg == 6
    assert box.append(crab(9)) == 7  # the appender sees the sender's seq
    assert [s.seq for s in queue.pending("mono_ir/crab")] == [5, 6, 7]
    assert queue.states() == {"acked": 2, "aggregated": 2}
    assert box.counts() == (7, 7, 3)
    assert queue.integrity_check() == []
    queue.close()
    box.close()


def test_seq_never_reused_after_purge(tmp_path: Path) -> None:
    path = tmp_path / "o.sqlite"
    box = Outbox(path)
    queue = OutboxQueue(path, OutboxConfig())
    for i in range(3):
        box.append(crab(i))
    queue.resolve([1, 2, 3], ACKED)
    assert queue.purge(keep_s=0.0) == 3
    assert box.append(crab(4)) == 4
    box.close()
    box = Outbox(path)
    assert box.append(crab(5)) == 5
    box.close()
    queue.close()


def test_checksum_catches_corruption(tmp_path: Path) -> None:
    path = tmp_path / "o.sqlite"
    box = Outbox(path)
    box.append(crab(1))
    box.append(crab(2))
    box.close()
    db = sqlite3.connect(path)
    db.execute("UPDATE records SET body=? WHERE seq=2", (b'{"mono_ir":{"seq":3}}',))
    db.commit()
    db.close()
    queue = OutboxQueue(path, OutboxConfig())
    assert [s.intact for s in queue.pending("mono_ir/crab")] == [True, False]
    assert queue.integrity_check() == ["record 2: checksum mismatch"]
    queue.close()


def test_quota_purges_resolved_then_refuses(tmp_path: Path) -> None:
    path = tmp_path / "o.sqlite"
    cfg = OutboxConfig(quota_bytes=1 << 16, min_free_bytes=0)
    box = Outbox(path, cfg)
    queue = OutboxQueue(path, cfg)
    big = {"health": {"pad": "x" * 2000}}
    with pytest.raises(OutboxFull):
        for _ in range(200):
            box.append(big)
    assert box.quota_alarm.startswith("outbox at ")
    assert box.stats()["refused"] == 1
    stored = box.counts()[1]
    queue.resolve(range(1, stored + 1), ACKED)
    box._quota_checked = 0.0  # check now rather than in a second
    box.append(big)  # resolved records made room
    assert box.quota_alarm == ""
    assert box.counts()[1] < stored
    box.close()
    queue.close()


@pytest.mark.parametrize(
    ("record", "error"),
    [
        ({"health": {"pad": "x" * 100}}, "expected a record of at most 64 bytes"),
    ],
)
def test_append_rejects(tmp_path: Path, record: dict[str, object], error: str) -> None:
    box = Outbox(tmp_path / "o.sqlite", OutboxConfig(max_record_bytes=64))
    with pytest.raises(OutboxFull, match=error):
        box.append(record)
    box.close()


def test_retention_keeps_recent_and_unresolved(tmp_path: Path) -> None:
    path = tmp_path / "o.sqlite"
    box = Outbox(path)
    queue = OutboxQueue(path, OutboxConfig(retention_s=60))
    for i in range(4):
        box.append(crab(i))
    now = 4 * 10**18
    queue.resolve([1], ACKED, now_ns=now - 120 * 10**9)
    queue.resolve([2], AGGREGATED, now_ns=now - 10 * 10**9)
    assert queue.purge(now_ns=now) == 1
    assert [s.seq for s in queue.read()] == [2, 3, 4]
    box.close()
    queue.close()


@pytest.mark.parametrize("umask", [0o000, 0o022, 0o077])
def test_outbox_files_have_the_run_directorys_modes_whatever_the_umask(
        tmp_path: Path, umask: int) -> None:
    """Pins the outbox following the umask (0666 under umask 0: anyone could read the
    results waiting for the modem, or rewrite them): the file, SQLite's -wal and -shm get
    the run directory's file mode (0640, as results.jsonl) and a folder it creates 0700."""
    import os
    import stat

    from trapflow.wire.endpoints import FILE_MODE, RUN_DIR_MODE

    old = os.umask(umask)
    try:
        box = Outbox(tmp_path / "new" / "outbox.sqlite")
        box.append(crab(1))
    finally:
        os.umask(old)
    try:
        mode = {p.name: stat.S_IMODE(p.stat().st_mode) for p in (tmp_path / "new").iterdir()}
        assert mode == {"outbox.sqlite": FILE_MODE, "outbox.sqlite-wal": FILE_MODE,
                        "outbox.sqlite-shm": FILE_MODE}, {k: oct(v) for k, v in mode.items()}
        assert stat.S_IMODE((tmp_path / "new").stat().st_mode) == RUN_DIR_MODE
    finally:
        box.close()
