"""Durable store-and-forward outbox: every result lands here before anything is sent.

One SQLite file in WAL mode shared by the appender (the normalizer) and the modem
sender, each its own process. Records are append-only and checksummed; the sender
marks them resolved (acknowledged, expired, aggregated) in a separate table. A fresh
outbox draws a random session id, kept in the file: the link carries it so the surface
tells this outbox's record numbers from those of an earlier one.

Two clocks: a record's `t_ns` is the wall clock at append, its label (and the aggregation
buckets'); every time-to-live, the retention of resolved records and the hourly byte budget
are measured on the outbox's own clock (`clock_ns`), the monotonic clock plus an offset
kept in the file: it never steps with the wall clock, and after a reboot (a power cut) it
goes on from the newest time the file holds, so the time the trap was off does not count.
Before, a step of the wall clock a day forward expired every waiting record at once.
"""

from __future__ import annotations

import contextlib
import logging
import os
import secrets
import shutil
import sqlite3
import struct
import threading
import time
import zlib
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import msgspec
import psutil

from trapflow.config.modem import OutboxConfig
from trapflow.errors import TrapflowError
from trapflow.modem.frame import SESSION_BYTES
from trapflow.runtime.files import is_disk_full

log = logging.getLogger(__name__)

# Values of resolved.state: why a record no longer waits to be sent.
ACKED = 1
EXPIRED = 2
AGGREGATED = 3
REJECTED = 4  # too large for the link, or its checksum failed
STATE_NAMES = {ACKED: "acked", EXPIRED: "expired", AGGREGATED: "aggregated", REJECTED: "rejected"}

_SCHEMA = """
CREATE TABLE IF NOT EXISTS records(
    seq INTEGER PRIMARY KEY AUTOINCREMENT,  -- monotonic, never reused (AUTOINCREMENT)
    t_ns INTEGER NOT NULL,                  -- wall clock at append: a label
    cls TEXT NOT NULL,                      -- message class, e.g. stereo_ir/scallop
    body BLOB NOT NULL,                     -- the record as JSON
    crc INTEGER NOT NULL,                   -- crc32 of seq, t_ns, cls and body
    up_ns INTEGER NOT NULL DEFAULT 0        -- the outbox's clock at append: time-to-live
);
CREATE INDEX IF NOT EXISTS records_cls ON records(cls, seq);
CREATE TABLE IF NOT EXISTS resolved(
    seq INTEGER PRIMARY KEY,
    state INTEGER NOT NULL,
    t_ns INTEGER NOT NULL                   -- the outbox's clock when resolved: retention
);
CREATE TABLE IF NOT EXISTS tried(           -- records sent at least once: never aggregated
    seq INTEGER PRIMARY KEY
);
CREATE TABLE IF NOT EXISTS meta(           -- the outbox's identity: 'session' -> 4 bytes
    key TEXT PRIMARY KEY,
    value BLOB NOT NULL
);
CREATE TABLE IF NOT EXISTS sent(            -- link ledger for the hourly byte budget
    t_ns INTEGER NOT NULL,                  -- the outbox's clock when sent
    bytes INTEGER NOT NULL
);
"""

_PACK = struct.Struct("<qq")
# The free space the outbox leaves on its disk: this share of the partition, at most
# outbox.min_free_bytes. Before, the fixed 64 MB reserve on a small partition refused every
# record from the first (3,097 refusals in 200 s; the surface heard only health).
MIN_FREE_SHARE = 0.05


class OutboxFull(TrapflowError):
    """The outbox is at its quota (or the disk is nearly full): the record was not stored."""


class OutboxError(TrapflowError):
    """The outbox file cannot be used as it is (its identity is damaged)."""


class Stored(msgspec.Struct, frozen=True):
    """One record as read back from the outbox."""

    seq: int
    t_ns: int
    cls: str
    body: bytes
    intact: bool
    up_ns: int = 0  # the outbox's clock at append (time-to-live)

    def record(self) -> dict[str, Any]:
        """The record as a dict (the normalizer's JSON shape)."""
        value = msgspec.json.decode(self.body)
        if not isinstance(value, dict):
            raise ValueError(f"expected a JSON object in record {self.seq}, got {type(value)}")
        return value


def message_class(record: dict[str, Any], class_fields: dict[str, str]) -> str:
    """The class a record is prioritised by: `stereo_ir/scallop`, `health`, `stereo_vo`..."""
    if len(record) != 1:
        return "other"
    key, body = next(iter(record.items()))
    if not isinstance(body, dict):
        return str(key)
    if key == "aggregate" and isinstance(body.get("class"), str):
        return str(body["class"])
    field = class_fields.get(key)
    if field is not None and isinstance(body.get(field), str):
        return f"{key}/{body[field]}"
    return str(key)


def min_free_bytes(folder: Path, most: int) -> int:
    """The free space the outbox leaves on the disk of `folder`: MIN_FREE_SHARE of its
    partition, at most `most` (outbox.min_free_bytes)."""
    return min(most, int(shutil.disk_usage(folder).total * MIN_FREE_SHARE))


def record_crc(seq: int, t_ns: int, cls: str, body: bytes) -> int:
    """The checksum stored with every record."""
    return zlib.crc32(body, zlib.crc32(cls.encode(), zlib.crc32(_PACK.pack(seq, t_ns))))


def _connect(path: Path) -> sqlite3.Connection:
    """Open (or create) the outbox file with the run directory's modes, whatever the umask:
    a folder it creates is its owner's alone, the file (and SQLite's -wal and -shm, which
    SQLite creates with the file's own mode) read-write for the owner, readable by the group,
    as results.jsonl is."""
    from trapflow.wire.endpoints import FILE_MODE, RUN_DIR_MODE

    if not path.parent.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        os.chmod(path.parent, RUN_DIR_MODE)
    with contextlib.suppress(FileExistsError):  # the sender and the normalizer race here
        os.close(os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, FILE_MODE))
    db = sqlite3.connect(str(path), isolation_level=None, timeout=10.0, check_same_thread=False)
    db.execute("PRAGMA journal_mode=WAL")
    for suffix in ("", "-wal", "-shm"):  # also those left under another umask
        name = f"{path}{suffix}"
        with contextlib.suppress(FileNotFoundError):
            if os.stat(name).st_uid == os.geteuid():  # another user's file stays as it is
                os.chmod(name, FILE_MODE)
    # NORMAL in WAL mode: a commit is written (survives a process crash) but not fsynced;
    # the outbox fsyncs the WAL itself on a bounded interval, and checkpoints stay safe.
    db.execute("PRAGMA synchronous=NORMAL")
    db.execute("PRAGMA journal_size_limit=4194304")
    db.executescript(_SCHEMA)
    return db


def _boot_id() -> bytes:
    """This boot's id (the monotonic clock restarts with it): the kernel's, or else the
    boot time to the second."""
    try:
        with open("/proc/sys/kernel/random/boot_id", "rb") as fh:
            return fh.read().strip()
    except OSError:
        return f"{psutil.boot_time():.0f}".encode()


def _clock_offset(db: sqlite3.Connection, now_ns: int, boot: bytes) -> int:
    """The outbox clock's offset from the monotonic clock: kept while the boot is the same;
    on a new boot (or a file from before the clock) chosen so the clock goes on from the
    newest time the file holds. Every opener agrees (one write transaction decides)."""
    db.execute("BEGIN IMMEDIATE")
    try:
        cols = {r[1] for r in db.execute("PRAGMA table_info(records)")}
        if "up_ns" not in cols:  # a file from before the outbox clock: start it now
            db.execute("ALTER TABLE records ADD COLUMN up_ns INTEGER NOT NULL DEFAULT 0")
            db.execute("UPDATE resolved SET t_ns = 0")
            db.execute("DELETE FROM sent")
        rows = dict(db.execute("SELECT key, value FROM meta WHERE key IN ('boot', 'clock')"))
        if rows.get("boot") == boot and "clock" in rows:
            offset = int(_PACK.unpack(bytes(rows["clock"]))[0])
        else:
            newest = max(int(db.execute(q).fetchone()[0] or 0) for q in (
                "SELECT MAX(up_ns) FROM records", "SELECT MAX(t_ns) FROM resolved",
                "SELECT MAX(t_ns) FROM sent"))
            offset = newest - now_ns
            db.executemany("INSERT OR REPLACE INTO meta(key, value) VALUES (?, ?)",
                           [("boot", boot), ("clock", _PACK.pack(offset, 0))])
        db.execute("COMMIT")
    except BaseException:
        db.execute("ROLLBACK")
        raise
    return offset


class _Store:
    """A connection to the outbox file plus the interval fsync of its WAL."""

    def __init__(self, path: str | Path, cfg: OutboxConfig) -> None:
        self.path = Path(path)
        self.cfg = cfg
        self._db = _connect(self.path)
        self._clock_offset = _clock_offset(self._db, time.monotonic_ns(), _boot_id())
        self._lock = threading.RLock()
        self._dirty = False
        self._last_sync = time.monotonic()
        self.syncs = 0
        self._fsync_dir()
        self.session = self._session()

    def _session(self) -> bytes:
        """The outbox's session id, drawn and stored (durably) by whoever opens it first."""
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                row = self._db.execute("SELECT value FROM meta WHERE key='session'").fetchone()
                if row is None:
                    value = secrets.token_bytes(SESSION_BYTES)
                    self._db.execute("INSERT INTO meta(key, value) VALUES ('session', ?)", (value,))
                    created = True
                else:
                    value, created = bytes(row[0]), False
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            if created:
                _Store.sync(self)  # an id the surface saw must not change after a power cut
                log.info("outbox %s: new session %s", self.path, value.hex())
        if len(value) != SESSION_BYTES:
            raise OutboxError(
                f"expected a {SESSION_BYTES}-byte session id in the meta table of outbox "
                f"{self.path}, got {len(value)} bytes; the file is damaged: move it aside "
                "(a new outbox gets a new session) and keep it for its unsent records"
            )
        return value

    def _fsync_dir(self) -> None:
        # A new file is only durable once its directory entry is.
        fd = os.open(self.path.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    def clock_ns(self) -> int:
        """The outbox's clock: every duration it measures (time-to-live, retention, the
        hourly budget) is a difference of two of its readings."""
        return time.monotonic_ns() + self._clock_offset

    def _next_seq(self) -> int:
        """The seq the next record gets; call inside a write transaction."""
        row = self._db.execute("SELECT seq FROM sqlite_sequence WHERE name='records'").fetchone()
        return (int(row[0]) if row else 0) + 1

    def sync(self) -> None:
        """fsync the WAL now: everything committed so far survives a power cut."""
        with self._lock:
            for suffix in ("-wal", ""):
                try:
                    fd = os.open(str(self.path) + suffix, os.O_RDONLY)
                except FileNotFoundError:
                    continue
                try:
                    os.fsync(fd)
                finally:
                    os.close(fd)
            self._dirty = False
            self._last_sync = time.monotonic()
            self.syncs += 1

    def _maybe_sync(self) -> None:
        if self._dirty and time.monotonic() - self._last_sync >= self.cfg.fsync_interval_s:
            self.sync()

    @contextlib.contextmanager
    def _transaction(self) -> Iterator[None]:
        """One write transaction (the caller holds the lock): all of it commits, or none."""
        self._db.execute("BEGIN IMMEDIATE")
        try:
            yield
            self._db.execute("COMMIT")
        except BaseException:
            self._db.execute("ROLLBACK")
            raise
        self._dirty = True

    def _write(self, sql: str, rows: Iterable[Sequence[Any]]) -> None:
        with self._lock:
            with self._transaction():
                self._db.executemany(sql, rows)
            self._maybe_sync()

    def used_bytes(self) -> int:
        """Bytes the outbox occupies: live pages plus the WAL."""
        with self._lock:
            pages = self._db.execute("PRAGMA page_count").fetchone()[0]
            free = self._db.execute("PRAGMA freelist_count").fetchone()[0]
            size = self._db.execute("PRAGMA page_size").fetchone()[0]
        try:
            wal = os.path.getsize(str(self.path) + "-wal")
        except OSError:
            wal = 0
        return int((pages - free) * size + wal)

    def counts(self) -> tuple[int, int, int]:
        """(last seq ever assigned, records stored, records still waiting to be sent)."""
        with self._lock:
            row = self._db.execute(
                "SELECT seq FROM sqlite_sequence WHERE name='records'"
            ).fetchone()
            stored = self._db.execute("SELECT COUNT(*) FROM records").fetchone()[0]
            resolved = self._db.execute(
                "SELECT COUNT(*) FROM resolved JOIN records USING(seq)"
            ).fetchone()[0]
        return (int(row[0]) if row else 0, int(stored), int(stored - resolved))

    def purge(self, now_ns: int | None = None, keep_s: float | None = None) -> int:
        """Delete resolved records older than the retention; returns how many went."""
        now_ns = self.clock_ns() if now_ns is None else now_ns
        keep = self.cfg.retention_s if keep_s is None else keep_s
        cutoff = now_ns - int(keep * 1e9)
        with self._lock, self._transaction():
            cur = self._db.execute(
                "DELETE FROM records WHERE seq IN (SELECT seq FROM resolved WHERE t_ns < ?)",
                (cutoff,),
            )
            gone = cur.rowcount
            self._db.execute(
                "DELETE FROM tried WHERE seq IN (SELECT seq FROM resolved WHERE t_ns < ?)",
                (cutoff,),
            )
            self._db.execute("DELETE FROM resolved WHERE t_ns < ?", (cutoff,))
            self._db.execute("DELETE FROM sent WHERE t_ns < ?", (now_ns - 7200 * 10**9,))
        return int(gone)

    def integrity_check(self) -> list[str]:
        """SQLite's own check plus every record's checksum; empty when all is well."""
        with self._lock:
            problems = [r[0] for r in self._db.execute("PRAGMA integrity_check") if r[0] != "ok"]
            for seq, t_ns, cls, body, crc in self._db.execute(
                "SELECT seq, t_ns, cls, body, crc FROM records"
            ):
                if record_crc(seq, t_ns, cls, bytes(body)) != crc:
                    problems.append(f"record {seq}: checksum mismatch")
        return problems

    def read(self, seqs: Sequence[int] | None = None) -> list[Stored]:
        """Records by seq (all records when seqs is None), checksums verified."""
        with self._lock:
            if seqs is None:
                rows = self._db.execute(
                    "SELECT seq, t_ns, cls, body, crc, up_ns FROM records ORDER BY seq"
                )
                return [_stored(r) for r in rows]
            out = []
            for seq in seqs:
                row = self._db.execute(
                    "SELECT seq, t_ns, cls, body, crc, up_ns FROM records WHERE seq=?", (seq,)
                ).fetchone()
                if row is not None:
                    out.append(_stored(row))
            return out

    def close(self) -> None:
        """Fsync what is pending and close the file."""
        with self._lock:
            if self._dirty:
                self.sync()
            self._db.close()


def _stored(row: tuple[int, int, str, bytes, int, int]) -> Stored:
    seq, t_ns, cls, body, crc, up_ns = row
    body = bytes(body)
    return Stored(seq, t_ns, cls, body, record_crc(seq, t_ns, cls, body) == crc, up_ns)


class Outbox(_Store):
    """The appending side, used in-process by the normalizer.

    `append()` returns the record's seq once the record is committed: from then on it
    survives a crash of any trapflow process (kill -9). It is *acknowledged as stored*
    (survives a power cut) once `durable_seq >= seq`, at most `fsync_interval_s` later:
    a background thread fsyncs the WAL on that interval whenever something is pending.
    """

    def __init__(self, path: str | Path, cfg: OutboxConfig | None = None) -> None:
        super().__init__(path, cfg or OutboxConfig())
        self.appended = 0
        self.refused = 0
        self.quota_alarm = ""
        self._last_seq = self.counts()[0]
        self._durable_seq = self._last_seq
        self._quota_checked = 0.0
        self._used_estimate = 0
        self.min_free_bytes = min_free_bytes(self.path.parent, self.cfg.min_free_bytes)
        self._stop = threading.Event()
        self._flusher = threading.Thread(target=self._flush_loop, name="outbox-fsync", daemon=True)
        self._flusher.start()

    @property
    def durable_seq(self) -> int:
        """Every record with seq up to this one has been fsynced."""
        return self._durable_seq

    def sync(self) -> None:
        with self._lock:
            last = self._last_seq
            super().sync()
            self._durable_seq = last

    def _flush_loop(self) -> None:
        while not self._stop.wait(self.cfg.fsync_interval_s / 2):
            with self._lock:
                self._maybe_sync()

    def _fits(self, used: int, free: int, incoming: int) -> bool:
        return used + incoming <= self.cfg.quota_bytes and free - incoming >= self.min_free_bytes

    def _check_quota(self, incoming: int) -> None:
        # Measure at most once a second, unless the estimate since the last measure nears the quota.
        now = time.monotonic()
        self._used_estimate += incoming + 64
        if (
            not self.quota_alarm
            and now - self._quota_checked < 1.0
            and self._used_estimate < self.cfg.quota_bytes * 0.9
        ):
            return
        self._quota_checked = now
        used = self._used_estimate = self.used_bytes()
        free = shutil.disk_usage(self.path.parent).free
        if self._fits(used, free, incoming):
            self.quota_alarm = ""
            return
        # Resolved records go first, whatever their age: they already reached the surface.
        gone = self.purge(keep_s=0.0)
        with self._lock:
            # Hand the freed pages back and shrink the WAL, which counts against the quota.
            self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        used = self._used_estimate = self.used_bytes()
        if self._fits(used, free, incoming):
            self.quota_alarm = ""
            return
        self.quota_alarm = (
            f"outbox at {used} of {self.cfg.quota_bytes} bytes, {free} bytes free on disk "
            f"(minimum {self.min_free_bytes}); purged {gone} resolved records"
        )
        raise OutboxFull(self.quota_alarm)

    def append(self, record: dict[str, Any]) -> int:
        """Store one record; returns its seq. Raises OutboxFull (counted) at the quota."""
        return self.append_many([record])[-1]

    def append_many(self, records: Sequence[dict[str, Any]]) -> list[int]:
        """Store records in one transaction; returns their seqs in order."""
        if not records:
            return []
        bodies = [msgspec.json.encode(r) for r in records]
        for body in bodies:
            if len(body) > self.cfg.max_record_bytes:
                self.refused += len(records)
                raise OutboxFull(
                    f"expected a record of at most {self.cfg.max_record_bytes} bytes of JSON, "
                    f"got {len(body)}"
                )
        try:
            self._check_quota(sum(len(b) for b in bodies))
            return self._insert(records, bodies)
        except OutboxFull:
            self.refused += len(records)
            raise
        except sqlite3.OperationalError as exc:  # the disk filled under the reserve
            if not is_disk_full(exc):
                raise
            self.refused += len(records)
            self.quota_alarm = f"the disk is full: {exc}"
            raise OutboxFull(self.quota_alarm) from exc

    def _insert(self, records: Sequence[dict[str, Any]], bodies: list[bytes]) -> list[int]:
        t_ns, up_ns = time.time_ns(), self.clock_ns()
        with self._lock:
            with self._transaction():
                # Read the counter inside the write lock: the sender also appends (aggregates).
                first = self._next_seq()
                rows = []
                for i, (rec, body) in enumerate(zip(records, bodies, strict=True)):
                    seq = first + i
                    cls = message_class(rec, self.cfg.class_fields)
                    rows.append((seq, t_ns, cls, body, record_crc(seq, t_ns, cls, body), up_ns))
                self._db.executemany(
                    "INSERT INTO records(seq, t_ns, cls, body, crc, up_ns) VALUES (?,?,?,?,?,?)",
                    rows,
                )
            self._last_seq = first + len(records) - 1
            self.appended += len(records)
            self._maybe_sync()
        return [r[0] for r in rows]

    def stats(self) -> dict[str, Any]:
        """Counters for the stats topic."""
        last, stored, backlog = self.counts()
        return {
            "last_seq": last,
            "durable_seq": self._durable_seq,
            "appended": self.appended,
            "refused": self.refused,
            "stored": stored,
            "backlog": backlog,
            "used_bytes": self.used_bytes(),
            "quota_bytes": self.cfg.quota_bytes,
            "quota_alarm": self.quota_alarm,
            "syncs": self.syncs,
        }

    def close(self) -> None:
        self._stop.set()
        self._flusher.join(timeout=2)
        with self._lock:
            if self._dirty:
                self.sync()
            self._db.close()


class OutboxQueue(_Store):
    """The sending side: pending records per class, resolution, the link ledger."""

    def classes(self, after: int = 0) -> list[str]:
        """Classes of the records with seq > after (the last seq seen: only new ones are read)."""
        with self._lock:
            rows = self._db.execute("SELECT DISTINCT cls FROM records WHERE seq > ?", (after,))
            return [r[0] for r in rows]

    def last_seq(self) -> int:
        """The last seq ever assigned."""
        with self._lock:
            row = self._db.execute(
                "SELECT seq FROM sqlite_sequence WHERE name='records'"
            ).fetchone()
            return int(row[0]) if row else 0

    def pending(self, cls: str, after: int = 0, limit: int = 64) -> list[Stored]:
        """Up to limit unresolved records of one class with seq > after, oldest first."""
        with self._lock:
            rows = self._db.execute(
                "SELECT seq, t_ns, cls, body, crc, up_ns FROM records WHERE cls=? AND seq>? "
                "AND seq NOT IN (SELECT seq FROM resolved) ORDER BY seq LIMIT ?",
                (cls, after, limit),
            )
            return [_stored(r) for r in rows]

    def floor(self) -> int:
        """The lowest unresolved seq (last seq + 1 when nothing waits)."""
        with self._lock:
            row = self._db.execute(
                "SELECT MIN(seq) FROM records WHERE seq NOT IN (SELECT seq FROM resolved)"
            ).fetchone()
            if row[0] is not None:
                return int(row[0])
            row = self._db.execute(
                "SELECT seq FROM sqlite_sequence WHERE name='records'"
            ).fetchone()
            return (int(row[0]) if row else 0) + 1

    def resolve(self, seqs: Iterable[int], state: int, now_ns: int | None = None) -> None:
        """Mark records acknowledged, expired, aggregated or rejected (idempotent); now_ns
        is on the outbox's clock (clock_ns), now when None."""
        t = self.clock_ns() if now_ns is None else now_ns
        self._write(
            "INSERT OR IGNORE INTO resolved(seq, state, t_ns) VALUES (?,?,?)",
            [(s, state, t) for s in seqs],
        )

    def expire(self, cls: str, before_ns: int, keep: Iterable[int] = ()) -> int:
        """Resolve as expired every waiting record of cls appended before before_ns (on the
        outbox's clock: clock_ns)."""
        kept = set(keep)
        with self._lock:
            seqs = [
                r[0]
                for r in self._db.execute(
                    "SELECT seq FROM records WHERE cls=? AND up_ns<? "
                    "AND seq NOT IN (SELECT seq FROM resolved)",
                    (cls, before_ns),
                )
                if r[0] not in kept
            ]
        if seqs:
            self.resolve(seqs, EXPIRED)
        return len(seqs)

    def replace(self, record: dict[str, Any], cls: str, covered: Sequence[int]) -> int:
        """Append an aggregate and resolve what it covers in one transaction; returns its seq."""
        body = msgspec.json.encode(record)
        t_ns, up_ns = time.time_ns(), self.clock_ns()
        with self._lock:
            with self._transaction():
                seq = self._next_seq()
                self._db.execute(
                    "INSERT INTO records(seq, t_ns, cls, body, crc, up_ns) VALUES (?,?,?,?,?,?)",
                    (seq, t_ns, cls, body, record_crc(seq, t_ns, cls, body), up_ns),
                )
                self._db.executemany(
                    "INSERT OR IGNORE INTO resolved(seq, state, t_ns) VALUES (?,?,?)",
                    [(s, AGGREGATED, up_ns) for s in covered],
                )
            self._maybe_sync()
        return seq

    def record_sent(self, nbytes: int, seqs: Sequence[int] = (), now_ns: int | None = None) -> None:
        """Add a transmission to the budget ledger (at now_ns on the outbox's clock, now when
        None) and note the records it carried."""
        t = self.clock_ns() if now_ns is None else now_ns
        with self._lock, self._transaction():
            self._db.execute("INSERT INTO sent(t_ns, bytes) VALUES (?,?)", (t, nbytes))
            self._db.executemany(
                "INSERT OR IGNORE INTO tried(seq) VALUES (?)", [(s,) for s in seqs]
            )

    def tried(self, seqs: Sequence[int]) -> set[int]:
        """Which of these records were sent at least once (they may be on the surface)."""
        with self._lock:
            return {
                s
                for s in seqs
                if self._db.execute("SELECT 1 FROM tried WHERE seq=?", (s,)).fetchone()
            }

    def sent_since(self, since_ns: int) -> list[tuple[int, int]]:
        """(t_ns, bytes) of transmissions since a time on the outbox's clock, oldest first."""
        with self._lock:
            rows = self._db.execute(
                "SELECT t_ns, bytes FROM sent WHERE t_ns>=? ORDER BY t_ns", (since_ns,)
            )
            return [(int(a), int(b)) for a, b in rows]

    def states(self) -> dict[str, int]:
        """How many records are resolved in each way."""
        with self._lock:
            rows = self._db.execute("SELECT state, COUNT(*) FROM resolved GROUP BY state")
            return {STATE_NAMES.get(s, str(s)): int(n) for s, n in rows}

    def tick(self) -> None:
        """Fsync if the interval has passed (the sender calls this from its loop)."""
        with self._lock:
            self._maybe_sync()
