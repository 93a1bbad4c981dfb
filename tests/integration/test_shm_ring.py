"""Frame ring across real processes: byte-identical zero-copy reads, reuse detection with a
slow reader and under a racing writer, kill -9 of readers and writers holding slots, and
no segment left over a hundred kill -9'd creators once stale cleanup runs."""

from __future__ import annotations

import hashlib
import multiprocessing as mp
import os
import signal
import time
from collections.abc import Callable, Iterator
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
import pytest

from tests import builders
from trapflow.wire import frame_msgs, messages
from trapflow.wire import frame_ring as fr

pytestmark = pytest.mark.slow  # starts whole pipelines

SPAWN = mp.get_context("spawn")


@pytest.fixture
def procs() -> Iterator[Callable[..., tuple[Any, Connection]]]:
    """Start spawn-context children connected by a pipe; kill and join leftovers at the end."""
    started: list[Any] = []

    def _start(target: Callable[..., None], *args: Any) -> tuple[Any, Connection]:
        here, there = SPAWN.Pipe()
        p = SPAWN.Process(target=target, args=(*args, there), daemon=True)
        p.start()
        there.close()
        started.append(p)
        return p, here

    yield _start
    for p in started:
        if p.is_alive():
            p.kill()
        p.join(5)
    assert not [p.pid for p in started if p.is_alive()], "child processes left behind"


def recv_bytes(conn: Connection, timeout: float = 10.0) -> bytes:
    if not conn.poll(timeout):
        raise AssertionError(f"nothing from the child within {timeout} s")
    return conn.recv_bytes()


# --- children (module level, so spawn can import them) ------------------------------------


def _hashing_reader(name: str, conn: Connection) -> None:
    """For each FrameRef: sha256 of left and right read in place, then the reuse check."""
    reader = fr.RingReader(name)
    while data := conn.recv_bytes():
        ref = frame_msgs.decode_frame_ref(data)
        with reader.pair(ref) as (left, right):
            digest = (hashlib.sha256(left).hexdigest() + hashlib.sha256(right).hexdigest())
        conn.send_bytes(digest.encode())


def _slow_reader(name: str, conn: Connection) -> None:
    """Views a pair, says so, waits to be told to go on, then checks (forced slow reader)."""
    reader = fr.RingReader(name)
    ref = frame_msgs.decode_frame_ref(conn.recv_bytes())
    left, _right = reader.view(ref)
    seen = left.tobytes()
    conn.send_bytes(b"viewing")
    conn.recv_bytes()
    outcomes = []
    try:
        reader.check(ref)
        outcomes.append("accepted")
    except fr.StaleFrame:
        outcomes.append("stale-after")
    try:
        reader.view(ref)
        outcomes.append("accepted")
    except fr.StaleFrame:
        outcomes.append("stale-before")
    outcomes += [f"rejected={reader.rejected}", f"changed={seen != left.tobytes()}"]
    conn.send_bytes(" ".join(outcomes).encode())


def _verifying_reader(name: str, conn: Connection) -> None:
    """Ask for the newest pair, verify every byte against the counter in its first 8 bytes,
    then check; a read that passes the check with wrong bytes is a torn read."""
    reader = fr.RingReader(name)
    accepted = torn = 0
    while True:
        conn.send_bytes(b"more")
        data = conn.recv_bytes()
        if not data:
            break
        ref = frame_msgs.decode_frame_ref(data)
        try:
            left, right = reader.view(ref)
            k = int(left[:8].view(np.uint64)[0])
            ok = bool(np.all(left[8:] == k % 251) and np.all(right == (k + 1) % 251))
            reader.check(ref)
        except fr.StaleFrame:
            continue
        accepted += 1
        torn += not ok
    conn.send_bytes(f"{accepted} {reader.rejected} {torn}".encode())


def _holding_reader(name: str, conn: Connection) -> None:
    """Views every pair it is sent and keeps the views until it is killed."""
    reader = fr.RingReader(name)
    held = []
    while data := conn.recv_bytes():
        held.append(reader.view(frame_msgs.decode_frame_ref(data)))
    conn.send_bytes(f"holding {len(held)}".encode())
    signal.pause()


def _crashing_writer(name: str, conn: Connection) -> None:
    """Commits one pair, acquires two more slots, then waits to be killed mid-write."""
    writer = fr.RingWriter(name)
    slot = writer.acquire()
    assert slot is not None
    conn.send_bytes(messages.encode(writer.write(slot, b"left", b"right")))
    writer.acquire()
    writer.acquire()
    conn.send_bytes(b"writing")
    signal.pause()


# --- tests ----------------------------------------------------------------------------------


def sha(b: bytes) -> str:
    return hashlib.sha256(b).hexdigest()


@pytest.mark.timeout(60)
def test_reads_across_processes_are_byte_identical(prefix: str, procs: Any) -> None:
    """Real JPEGs and raw images, written once, read in place by another process."""
    w, h = 320, 240
    with fr.FrameRing.create(4, fr.slot_capacity(w, h), prefix=prefix) as ring:
        writer = fr.RingWriter(ring.name)
        _p, conn = procs(_hashing_reader, ring.name)
        for i in range(24):
            left, right = builders.image(w, h, seed=i), builders.image(w, h, seed=i + 100)
            if i % 2:
                lb, rb = builders.jpeg(left), builders.jpeg(right)
            else:
                lb, rb = left.tobytes(), right.tobytes()
            slot = writer.acquire()
            assert slot is not None
            ref = writer.write(slot, lb, rb)
            conn.send_bytes(messages.encode(ref))
            assert recv_bytes(conn).decode() == sha(lb) + sha(rb)
            assert ring.free_ref(ref)
        conn.send_bytes(b"")
        assert ring.counts()["free"] == 4
        writer.close()


@pytest.mark.timeout(60)
def test_slow_reader_detects_that_its_slot_was_reused(prefix: str, procs: Any) -> None:
    with fr.FrameRing.create(1, 1024, prefix=prefix) as ring:
        writer = fr.RingWriter(ring.name)
        p, conn = procs(_slow_reader, ring.name)
        slot = writer.acquire()
        assert slot is not None
        conn.send_bytes(messages.encode(writer.write(slot, b"first-left", b"first-right")))
        assert recv_bytes(conn) == b"viewing"
        # The owner frees the pair (say, evicted on timeout) and capture reuses the slot
        # while the reader is still working on it.
        ring.free(slot, ring.generation(slot))
        again = writer.acquire()
        assert again == slot
        writer.write(again, b"second-left", b"second-right")
        conn.send_bytes(b"go")
        assert recv_bytes(conn).decode() == "stale-after stale-before rejected=2 changed=True"
        p.join(10)
        writer.close()


@pytest.mark.timeout(60)
def test_racing_writer_never_yields_a_torn_read(prefix: str, procs: Any) -> None:
    """The writer rewrites the slots as fast as it can while the reader verifies a pair:
    many reads are rejected, and no read that passes the check has mixed bytes. In quiet
    rounds the writer waits for the reader, so those reads must all be accepted."""
    n = 256 * 1024
    with fr.FrameRing.create(2, 2 * n, prefix=prefix) as ring:
        writer = fr.RingWriter(ring.name)
        p, conn = procs(_verifying_reader, ring.name)
        left, right = np.empty(n, np.uint8), np.empty(n, np.uint8)
        k = reads = quiet = 0
        last: frame_msgs.FrameRef | None = None
        # Two seconds of racing, and at least 8 reads (2 quiet rounds): the reader process may
        # take seconds to start on a loaded machine.
        t_end, t_limit = time.monotonic() + 2.0, time.monotonic() + 40.0
        while (time.monotonic() < t_end or last is None or reads < 8) \
                and time.monotonic() < t_limit:
            slot = writer.acquire()
            assert slot is not None  # freed right after each write: never full
            left[8:] = k % 251
            left[:8].view(np.uint64)[0] = k
            right[:] = (k + 1) % 251
            last = writer.write(slot, left, right)
            ring.free_ref(last)  # worst case: the owner frees at once, capture reuses soon
            k += 1
            if conn.poll(0):
                conn.recv_bytes()
                conn.send_bytes(messages.encode(last))
                reads += 1
                if reads % 4 == 0:  # a quiet round: no write until the reader has finished
                    quiet += 1
                    assert conn.poll(10)
        recv_bytes(conn)
        conn.send_bytes(b"")
        accepted, rejected, torn = map(int, recv_bytes(conn).split())
        p.join(10)
        writer.close()
    assert torn == 0
    assert accepted + rejected == reads
    assert accepted >= quiet > 0


@pytest.mark.timeout(60)
def test_kill9_of_a_reader_holding_slots_then_the_owner_frees_them(
        prefix: str, procs: Any) -> None:
    """A worker dies holding views of every slot; the lifetime owner (the broker, on the
    eviction) frees its pairs and capture gets every slot back."""
    with fr.FrameRing.create(4, 4096, prefix=prefix) as ring:
        writer = fr.RingWriter(ring.name)
        p, conn = procs(_holding_reader, ring.name)
        refs = []
        for i in range(4):
            slot = writer.acquire()
            assert slot is not None
            refs.append(writer.write(slot, f"left{i}".encode(), f"right{i}".encode()))
            conn.send_bytes(messages.encode(refs[-1]))
        conn.send_bytes(b"")
        assert recv_bytes(conn) == b"holding 4"
        assert writer.acquire() is None  # full: capture would drop and count
        os.kill(p.pid, signal.SIGKILL)
        p.join(10)
        assert p.exitcode == -signal.SIGKILL
        assert ring.counts() == {"free": 0, "writing": 0, "held": 4}
        assert all(ring.free_ref(r) for r in refs)
        assert ring.counts() == {"free": 4, "writing": 0, "held": 0}
        slots = {writer.acquire() for _ in range(4)}
        assert slots == {0, 1, 2, 3}
        assert writer.acquire() is None
        writer.close()


@pytest.mark.timeout(60)
def test_kill9_of_a_writer_mid_write_is_reclaimed_by_the_next(prefix: str,
                                                              procs: Any) -> None:
    with fr.FrameRing.create(4, 4096, prefix=prefix) as ring:
        p, conn = procs(_crashing_writer, ring.name)
        committed = frame_msgs.decode_frame_ref(recv_bytes(conn))
        assert recv_bytes(conn) == b"writing"
        os.kill(p.pid, signal.SIGKILL)
        p.join(10)
        assert ring.counts() == {"free": 1, "writing": 2, "held": 1}
        writer = fr.RingWriter(ring.name)  # capture restarted
        assert ring.counts() == {"free": 3, "writing": 0, "held": 1}
        reader = fr.RingReader(ring.name)
        with reader.pair(committed) as (left, right):
            assert (left.tobytes(), right.tobytes()) == (b"left", b"right")
        assert ring.free_ref(committed)
        del left, right
        reader.close()
        writer.close()


def _fork_creator(prefix: str) -> tuple[int, int]:
    """Fork a process that creates a ring, reports its name on a pipe, and waits."""
    rfd, wfd = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: never returns into pytest
        code = 1
        try:
            os.close(rfd)
            ring = fr.FrameRing.create(4, 256 * 1024, prefix=prefix)
            os.write(wfd, ring.name.encode())
            signal.pause()
        finally:
            os._exit(code)
    os.close(wfd)
    return pid, rfd


@pytest.mark.timeout(90)
def test_hundred_kill9_creators_leave_nothing_after_stale_cleanup(prefix: str) -> None:
    """Creators killed with SIGKILL cannot unlink: their segments stay until the next start
    runs cleanup_stale, which must remove every one of them, so /dev/shm does not grow."""
    cycles, per_start = 100, 10
    left_behind = removed = 0
    for i in range(cycles):
        pid, rfd = _fork_creator(prefix)
        try:
            # Half are killed once the segment exists, half at once (maybe mid-creation).
            if i % 2 == 0:
                assert os.read(rfd, 200).startswith(prefix.encode())
                left_behind += 1
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
        finally:
            os.close(rfd)
        if (i + 1) % per_start == 0:  # a new run starts
            present = fr.list_segments(prefix)
            assert len(present) >= per_start // 2
            gone = fr.cleanup_stale(prefix)
            assert sorted(gone) == present
            removed += len(gone)
            assert fr.list_segments(prefix) == []
    assert removed >= left_behind == cycles // 2
    assert fr.cleanup_stale(prefix) == []
