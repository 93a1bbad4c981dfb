"""Stereo pairs in shared memory: a ring of pre-faulted fixed-size slots in one POSIX
segment, written once by capture and read in place (zero-copy numpy views) by workers.
Owns no sockets; only FrameRef descriptors (trapflow/wire/messages.py) travel over ZeroMQ.

Segment layout (Linux, a file under /dev/shm named
`trapflow-<owner pid>-<owner pid namespace>-<boot id>-<token>`):
    [segment header | one state byte per slot | pad to a page] [slot 0] [slot 1] ...
    slot = [generation u64 | left length u64 | right length u64 | pad to 64] [left | right]

Slot states and who moves them (one writer per transition, so no cross-process lock):
    FREE -> WRITING   capture, in acquire()
    WRITING -> HELD   capture, at the end of write() (or commit(), after begin() opened
                      the slot for a pair made in place)
    WRITING -> FREE   capture, release() of an abandoned write, or reclaim after a crash
    HELD -> FREE      the lifetime owner (the broker), free(slot, generation), when no pool
                      holds the pair any more; capture's release() when it is told instead
A state is one byte: single-byte stores and loads are atomic on every CPU we run on.

Memory ordering (a seqlock per slot). The writer makes the generation odd, fences, copies
the payload, fences, then makes it even; the descriptor carries that even value. A reader
checks the generation before handing out views and again (after a fence) when done: any
reuse bumps it first, so an unchanged even value proves the bytes it used were that pair's.
The fence is an uncontended lock acquire+release: an atomic read-modify-write with acquire
and release ordering in every CPython build, which orders loads and stores on ARM too (x86
needs none). Generations are aligned 8-byte words, loaded and stored in one access.

Cleanup: the creator unlinks the segment at close(). A creator killed with SIGKILL cannot;
its segment stays until the next start calls cleanup_stale(), which removes a segment only
when its owner is provably gone (stale_verdict): created before this boot, or in this pid
namespace and this boot with its pid dead, a zombie, or reused by a newer process. A pid
means nothing across pid namespaces (containers sharing /dev/shm): a segment of another
namespace, or of a name that does not say its namespace, is left alone (logged once).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import mmap
import os
import secrets
import struct
import threading
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from trapflow.config.schema import FramesConfig, PoolConfig  # noqa: F401 - FramesConfig re-exported
from trapflow.errors import ProtocolError, StartupError, TrapflowError
from trapflow.wire.frame_msgs import FRAME_SLOT_HEADER, MAX_RING_SLOTS, FrameRef, check_frame_ref

log = logging.getLogger(__name__)

SHM_DIR = "/dev/shm"  # where Linux keeps POSIX shared-memory objects
PREFIX = "trapflow-"
PAGE = mmap.PAGESIZE
ALIGN = 64  # payloads start on cache-line boundaries

FREE, WRITING, HELD = 0, 1, 2
STATE_NAMES = {FREE: "free", WRITING: "writing", HELD: "held"}

_MAGIC = b"TFRING\x00\x01"
# magic, nslots, pad, slot_size, capacity, owner pid, owner start ticks, data offset
_HEADER = struct.Struct("<8sIIQQQQQ")
_STATES_AT = 64  # the state bytes follow the header
_FREE_BYTE = bytes([FREE])
# Pairs between capture and the broker (capture's send queue, the broker's receive queue)
# and the one capture is writing: they hold slots no pool knows of yet.
IN_TRANSIT_SLOTS = 9


class RingError(TrapflowError):
    """A frame ring cannot be created, opened or written."""


class StaleFrame(RingError):
    """The slot was reused while (or before) the reader used it: the read is rejected."""


def slot_capacity(width: int, height: int) -> int:
    """Payload bytes a slot needs for a pair: two raw BGR images (a bound for JPEG too)."""
    return width * height * 3 * 2


def ring_slots(pools: Iterable[PoolConfig], preroll: int = 0,
               spare: int = IN_TRANSIT_SLOTS) -> int:
    """Slots for every pool's in-flight (count x credit) and pending (policy bound) pairs,
    plus the pre-roll and the pairs in transit to the broker."""
    held = sum(p.count * p.credit + p.parsed_policy.bound for p in pools)
    return held + preroll + spare


@dataclass(frozen=True)
class SegmentOwner:
    """Who created a segment, as its name says: pid, pid namespace (inode) and boot id."""

    pid: int
    pidns: int
    boot: str


def own_pidns() -> int:
    """The inode of this process's pid namespace (0 where /proc does not say)."""
    try:
        link = os.readlink("/proc/self/ns/pid")  # "pid:[4026531836]"
        return int(link[link.index("[") + 1:link.index("]")])
    except (OSError, ValueError):
        return 0


def boot_id() -> str:
    """This boot of the kernel (the first 16 hex digits of its boot id; "0" if unknown).
    Every pid namespace of one kernel reads the same."""
    try:
        with open("/proc/sys/kernel/random/boot_id") as f:
            return f.read().strip().replace("-", "")[:16] or "0"
    except OSError:
        return "0"


def segment_name(owner_pid: int | None = None, prefix: str = PREFIX) -> str:
    """A new segment name that embeds the owning process, its pid namespace and the boot,
    so stale ones can be told apart from live ones of other containers."""
    pid = owner_pid if owner_pid is not None else os.getpid()
    return f"{prefix}{pid}-{own_pidns()}-{boot_id()}-{secrets.token_hex(4)}"


def owner_of(name: str, prefix: str = PREFIX) -> SegmentOwner | None:
    """The owner a segment's name records; None for a name without pid, namespace and
    boot (another program's, or one named before segments recorded them)."""
    parts = name[len(prefix):].split("-")
    if not name.startswith(prefix) or len(parts) != 4:
        return None
    pid, ns, boot, _token = parts
    if not (pid.isdigit() and ns.isdigit() and boot.isalnum()):
        return None
    return SegmentOwner(int(pid), int(ns), boot)


def stale_verdict(owner: SegmentOwner | None, pidns: int, boot: str, live_start: int | None,
                  header_start: int | None) -> tuple[bool, str]:
    """Whether a segment may be removed, and why (pure). `pidns` and `boot` are this
    process's; `live_start` the start time of a live process with the owner's pid here
    (None: no such process, or a zombie); `header_start` the owner's start time the header
    records (None: no header yet, 0: not recorded). Removed only when provably stale."""
    if owner is None:
        return False, "its name does not say its owner's pid namespace and boot"
    if owner.boot != boot:
        return True, "created before this boot"
    if owner.pidns != pidns:
        return False, "owned in another pid namespace, where its pid means another process"
    if live_start is None:
        return True, f"its owner (pid {owner.pid}) is gone"
    if header_start is None:
        return False, "being created (no header yet)"
    if header_start and header_start != live_start:
        return True, f"pid {owner.pid} now belongs to a newer process"
    return False, f"its owner (pid {owner.pid}) is alive"


def _round_up(n: int, to: int) -> int:
    return (n + to - 1) // to * to


def _proc_start_ticks(pid: int) -> int | None:
    """The start time of a live process in clock ticks; None if it is gone or a zombie."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat = f.read()
    except OSError:
        return None
    fields = stat[stat.rfind(b")") + 2:].split()
    if not fields or fields[0] == b"Z":
        return None
    return int(fields[19])  # field 22 of stat; fields[0] is field 3


_fence_lock = threading.Lock()


def _fence() -> None:
    # See the module docstring: an atomic RMW with acquire and release ordering.
    _fence_lock.acquire()
    _fence_lock.release()


class FrameRing:
    """A mapped ring segment. Attach with FrameRing(name); create with FrameRing.create().

    The base role frees slots (free()) for whoever owns pair lifetime; RingWriter and
    RingReader add capture's and the workers' operations.
    """

    def __init__(self, name: str, *, writable: bool = True, shm_dir: str = SHM_DIR) -> None:
        if "/" in name or not name:
            raise RingError(f"expected a segment name without '/', got {name!r}")
        self.name = name
        self.path = os.path.join(shm_dir, name)
        self._owner = False
        try:
            fd = os.open(self.path, os.O_RDWR if writable else os.O_RDONLY)
        except OSError as exc:
            raise RingError(f"cannot open ring segment {name!r}: {exc.strerror}") from None
        try:
            size = os.fstat(fd).st_size
            head = os.pread(fd, _HEADER.size, 0)
            if len(head) < _HEADER.size:
                raise RingError(f"ring segment {name!r}: expected a header, got {size} bytes")
            magic, nslots, _, slot_size, capacity, pid, start, data_at = _HEADER.unpack(head)
            if magic != _MAGIC:
                raise RingError(f"ring segment {name!r}: expected magic {_MAGIC!r}, got {magic!r}")
            if (not 0 < nslots <= MAX_RING_SLOTS or slot_size % PAGE or data_at % PAGE
                    or data_at + nslots * slot_size != size):
                raise RingError(
                    f"ring segment {name!r}: inconsistent header ({nslots} slots of "
                    f"{slot_size} bytes at {data_at}) for a file of {size} bytes")
            prot = mmap.PROT_READ | (mmap.PROT_WRITE if writable else 0)
            # MAP_POPULATE maps every page now, so no read later takes a page fault.
            flags = mmap.MAP_SHARED | getattr(mmap, "MAP_POPULATE", 0)
            self._mm: mmap.mmap | None = mmap.mmap(fd, size, flags=flags, prot=prot)
        finally:
            os.close(fd)
        self.slots: int = nslots
        self.slot_size: int = slot_size
        self.capacity: int = capacity
        self.owner_pid: int = pid
        self.owner_start: int = start
        self.size = size
        self._states = np.ndarray((nslots,), np.uint8, self._mm, _STATES_AT)
        self._data = np.ndarray((nslots, slot_size), np.uint8, self._mm, data_at)
        self._words = self._data.view(np.uint64)  # [slot, 0] generation, [1] left, [2] right

    @classmethod
    def create(cls, slots: int, capacity: int, *, prefix: str = PREFIX,
               owner_pid: int | None = None, shm_dir: str = SHM_DIR) -> FrameRing:
        """Create, reserve and pre-fault a segment of `slots` slots of `capacity` payload
        bytes; the returned ring owns it (close() unlinks). StartupError if memory is short."""
        if not 0 < slots <= MAX_RING_SLOTS:
            raise RingError(f"expected 1..{MAX_RING_SLOTS} slots, got {slots}")
        if capacity < 2:
            raise RingError(f"expected a slot capacity of at least 2 bytes, got {capacity}")
        pid = owner_pid if owner_pid is not None else os.getpid()
        start = _proc_start_ticks(pid) or 0
        name = segment_name(pid, prefix)
        slot_size = _round_up(FRAME_SLOT_HEADER + capacity + ALIGN, PAGE)
        data_at = _round_up(_STATES_AT + slots, PAGE)
        size = data_at + slots * slot_size
        path = os.path.join(shm_dir, name)
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            try:
                # Reserve the memory now: a full tmpfs is an error here, not a SIGBUS later.
                os.posix_fallocate(fd, 0, size)
            except OSError as exc:
                raise StartupError(
                    f"cannot reserve {size} bytes of shared memory for {slots} slots of "
                    f"{slot_size} bytes: {exc.strerror}") from None
            os.pwrite(fd, _HEADER.pack(_MAGIC, slots, 0, slot_size, capacity, pid, start,
                                       data_at), 0)
            ring = cls(name, shm_dir=shm_dir)
        except BaseException:
            os.close(fd)
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)
            raise
        os.close(fd)
        ring._owner = True
        ring._data[:, ::PAGE] = 0  # pre-fault: one write per page
        log.info("frame ring %s: %d slots of %d bytes (%.1f MB)", name, slots, slot_size,
                 size / 1e6)
        return ring

    # --- state ----------------------------------------------------------------------

    def generation(self, slot: int) -> int:
        """The slot's generation now (even: committed, odd: being written)."""
        return int(self._words[slot, 0])

    def state(self, slot: int) -> int:
        """FREE, WRITING or HELD."""
        return int(self._states[slot])

    def counts(self) -> dict[str, int]:
        """How many slots are free, being written and held."""
        hist = np.bincount(self._states, minlength=3)
        return {STATE_NAMES[s]: int(hist[s]) for s in (FREE, WRITING, HELD)}

    def free(self, slot: int, generation: int) -> bool:
        """The lifetime owner's release: no pool holds this pair any more. False (and no
        change) if the slot no longer holds that generation: a repeated free is harmless."""
        if not 0 <= slot < self.slots:
            raise ProtocolError(f"free: expected slot in 0..{self.slots - 1}, got {slot}")
        # Only this role moves a HELD slot, so the check and the store cannot race.
        if self._states[slot] != HELD or int(self._words[slot, 0]) != generation:
            return False
        self._states[slot] = FREE
        return True

    def free_held(self) -> int:
        """Free every HELD slot (a new lifetime owner knows of no pair); how many."""
        return sum(self.free(slot, self.generation(slot))
                   for slot in range(self.slots) if self.state(slot) == HELD)

    def free_ref(self, ref: FrameRef) -> bool:
        """free() the slot a descriptor points to."""
        return self.free(ref.slot, ref.generation)

    def validate(self, ref: FrameRef) -> None:
        """ProtocolError unless the descriptor names this segment and lies inside a slot."""
        if ref.segment != self.name:
            raise ProtocolError(
                f"frame ref: expected segment {self.name!r}, got {ref.segment!r}")
        check_frame_ref(ref, self.slots, self.slot_size)

    def payload(self, ref: FrameRef) -> tuple[np.ndarray, np.ndarray]:
        """Views of a pair for its lifetime owner, who keeps the slot held while using them."""
        self.validate(ref)
        row = self._data[ref.slot]
        return (row[ref.left_offset:ref.left_offset + ref.left_length],
                row[ref.right_offset:ref.right_offset + ref.right_length])

    # --- lifetime ---------------------------------------------------------------------

    @property
    def owner(self) -> bool:
        """Whether this handle created the segment (and unlinks it at close)."""
        return self._owner

    def close(self) -> None:
        """Unmap; the creator also unlinks. Views handed out must be dropped first (a view
        still alive keeps the mapping, which the kernel frees when the last one goes)."""
        if self._owner:
            self._owner = False
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.path)
        mm, self._mm = self._mm, None
        if mm is None:
            return
        del self._states, self._data, self._words
        try:
            mm.close()
        except BufferError:
            log.debug("ring %s: views still alive; unmapped when they go", self.name)

    def __enter__(self) -> FrameRing:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _as_bytes(buf: Any) -> np.ndarray:
    if isinstance(buf, np.ndarray):
        return np.ascontiguousarray(buf).reshape(-1).view(np.uint8)
    return np.frombuffer(buf, np.uint8)


class RingWriter(FrameRing):
    """Capture's side: take a free slot, write a pair once, hand out its descriptor.
    One writer per segment at a time; attaching reclaims slots a crashed writer left."""

    def __init__(self, name: str, *, shm_dir: str = SHM_DIR) -> None:
        super().__init__(name, writable=True, shm_dir=shm_dir)
        self._cursor = 0
        self.full = 0  # acquire() calls that found no free slot
        self.reclaim()

    def reclaim(self) -> int:
        """Free slots left WRITING (a writer died mid-write); returns how many."""
        stuck = np.flatnonzero(self._states == WRITING)
        for slot in stuck:
            gen = int(self._words[slot, 0])
            if gen % 2:
                self._words[slot, 0] = gen + 1  # back to even, still newer than any ref
            self._states[slot] = FREE
        return len(stuck)

    def acquire(self) -> int | None:
        """A free slot, now WRITING; None when every slot is taken (drop the pair, count it).
        Slots are taken round robin so a freed slot waits longest before reuse."""
        mm = self._mm
        assert mm is not None
        # mmap.find scans the state bytes in C: a fraction of a microsecond for any ring.
        end = _STATES_AT + self.slots
        at = mm.find(_FREE_BYTE, _STATES_AT + self._cursor, end)
        if at < 0:
            at = mm.find(_FREE_BYTE, _STATES_AT, end)
        if at < 0:
            self.full += 1
            return None
        slot = at - _STATES_AT
        self._cursor = slot + 1
        self._states[slot] = WRITING
        return slot

    def write(self, slot: int, left: Any, right: Any) -> FrameRef:
        """Copy both images into an acquired slot (one copy each), commit, return the
        descriptor. RingError if the slot was not acquired or the pair does not fit."""
        lb, rb = _as_bytes(left), _as_bytes(right)
        left_view, right_view = self.begin(slot, lb.nbytes, rb.nbytes)
        left_view[:] = lb
        right_view[:] = rb
        return self.commit(slot)

    def begin(self, slot: int, left_nbytes: int, right_nbytes: int
              ) -> tuple[np.ndarray, np.ndarray]:
        """Open an acquired slot for a pair of these sizes: writable uint8 views of its left
        and right payloads, for a producer that makes the images in place (a decoder or a
        camera buffer written straight into the slot: no copy); commit() publishes them.
        RingError if the slot was not acquired or the pair does not fit."""
        if not 0 <= slot < self.slots or self._states[slot] != WRITING:
            raise RingError(f"write: expected an acquired slot, got {slot}")
        loff = FRAME_SLOT_HEADER
        roff = _round_up(loff + left_nbytes, ALIGN)
        if (left_nbytes <= 0 or right_nbytes <= 0
                or left_nbytes + right_nbytes > self.capacity
                or roff + right_nbytes > self.slot_size):
            raise RingError(
                f"write: expected 1..{self.capacity} payload bytes per pair, got "
                f"{left_nbytes} + {right_nbytes}")
        words = self._words
        gen = int(words[slot, 0])
        if gen % 2 == 0:
            words[slot, 0] = gen + 1  # odd: readers of the old pair see the reuse
            _fence()
        words[slot, 1] = left_nbytes
        words[slot, 2] = right_nbytes
        row = self._data[slot]
        return row[loff:loff + left_nbytes], row[roff:roff + right_nbytes]

    def commit(self, slot: int) -> FrameRef:
        """Publish the pair begin() opened in `slot`: HELD, and its descriptor. RingError if
        begin() did not open it."""
        words = self._words
        gen = int(words[slot, 0]) if 0 <= slot < self.slots else 0
        if gen % 2 == 0 or self._states[slot] != WRITING:
            raise RingError(f"commit: expected a slot opened by begin(), got {slot}")
        ln, rn = int(words[slot, 1]), int(words[slot, 2])
        _fence()
        words[slot, 0] = gen + 1
        self._states[slot] = HELD
        loff = FRAME_SLOT_HEADER
        return FrameRef(segment=self.name, slot=slot, generation=gen + 1, left_offset=loff,
                        left_length=ln, right_offset=_round_up(loff + ln, ALIGN),
                        right_length=rn)

    def release(self, slot: int) -> None:
        """Put a slot back on the free list: an acquired slot whose write was abandoned,
        or a held one when the lifetime owner tells capture (instead of calling free())."""
        if not 0 <= slot < self.slots:
            raise ProtocolError(f"release: expected slot in 0..{self.slots - 1}, got {slot}")
        if self._states[slot] == WRITING:
            gen = int(self._words[slot, 0])
            if gen % 2:
                self._words[slot, 0] = gen + 1
        self._states[slot] = FREE


class RingReader(FrameRing):
    """A worker's side: map once (read-only), read pairs as zero-copy views, and check
    after use that the slot was not reused underneath (rejected reads are counted)."""

    def __init__(self, name: str, *, shm_dir: str = SHM_DIR) -> None:
        super().__init__(name, writable=False, shm_dir=shm_dir)
        self.rejected = 0

    def view(self, ref: FrameRef) -> tuple[np.ndarray, np.ndarray]:
        """Read-only uint8 views of the left and right payloads. ProtocolError for a bad
        descriptor, StaleFrame if the slot already holds a newer pair."""
        self.validate(ref)
        if int(self._words[ref.slot, 0]) != ref.generation:
            self.rejected += 1
            raise StaleFrame(f"slot {ref.slot}: expected generation {ref.generation}, "
                             f"got {int(self._words[ref.slot, 0])} before the read")
        _fence()
        row = self._data[ref.slot]
        return (row[ref.left_offset:ref.left_offset + ref.left_length],
                row[ref.right_offset:ref.right_offset + ref.right_length])

    def check(self, ref: FrameRef) -> None:
        """After using the views: StaleFrame if the slot was reused meanwhile (the result
        computed from it must be discarded)."""
        _fence()
        gen = int(self._words[ref.slot, 0])
        if gen != ref.generation:
            self.rejected += 1
            raise StaleFrame(f"slot {ref.slot}: expected generation {ref.generation}, "
                             f"got {gen} after the read (reused while in use)")

    @contextlib.contextmanager
    def pair(self, ref: FrameRef) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """`with reader.pair(ref) as (left, right): ...` then check() on a normal exit."""
        views = self.view(ref)
        yield views
        self.check(ref)


def list_segments(prefix: str = PREFIX, shm_dir: str = SHM_DIR) -> list[str]:
    """Names of the segments under shm_dir that start with prefix."""
    try:
        return sorted(n for n in os.listdir(shm_dir) if n.startswith(prefix))
    except FileNotFoundError:
        return []


def _header_start(name: str, shm_dir: str) -> int | None:
    """The owner start time a segment's header records; None while it has no header."""
    try:
        fd = os.open(os.path.join(shm_dir, name), os.O_RDONLY)
    except OSError:
        return None
    try:
        head = os.pread(fd, _HEADER.size, 0)
    finally:
        os.close(fd)
    if len(head) < _HEADER.size:
        return None  # being created right now (header not written yet)
    magic, *_, owner_start, _ = _HEADER.unpack(head)
    return int(owner_start) if magic == _MAGIC else 0


# Segments already said to be left alone (said once per process, not at every start).
_TOLD: set[str] = set()


def _is_stale(name: str, prefix: str, shm_dir: str) -> bool:
    owner = owner_of(name, prefix)
    live = _proc_start_ticks(owner.pid) if owner is not None else None
    header = _header_start(name, shm_dir) if owner is not None and live is not None else None
    remove, why = stale_verdict(owner, own_pidns(), boot_id(), live, header)
    if not remove and name not in _TOLD and (owner is None or "namespace" in why):
        _TOLD.add(name)
        log.info("left shared-memory segment %s alone: %s", name, why)
    return remove


def cleanup_stale(prefix: str = PREFIX, shm_dir: str = SHM_DIR) -> list[str]:
    """Remove segments whose owner process is gone; returns the names removed.
    The supervisor calls this at start, before creating its own segment."""
    removed = []
    for name in list_segments(prefix, shm_dir):
        if not _is_stale(name, prefix, shm_dir):
            continue
        try:
            os.unlink(os.path.join(shm_dir, name))
        except FileNotFoundError:
            continue  # another cleaner got there first
        except OSError as exc:
            if exc.errno in (errno.EPERM, errno.EACCES):
                log.warning("stale ring segment %s is not ours to remove: %s", name,
                            exc.strerror)
                continue
            raise
        removed.append(name)
    if removed:
        log.info("removed %d stale ring segment(s): %s", len(removed), ", ".join(removed))
    return removed
