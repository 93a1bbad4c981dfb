"""Frame ring in one process: writes and views, the free list, reuse detection,
descriptor validation, reclaim after a crashed writer, stale-segment cleanup, sizing."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable, Iterator

import msgspec
import numpy as np
import pytest

from tests import builders
from tests.conftest import only_pools
from trapflow.config import schema as configmod
from trapflow.errors import ProtocolError
from trapflow.wire import frame_msgs, messages
from trapflow.wire import frame_ring as fr

pytestmark = pytest.mark.timeout(30)


@pytest.fixture
def make_ring(prefix: str) -> Iterator[Callable[..., fr.FrameRing]]:
    rings: list[fr.FrameRing] = []

    def _make(slots: int = 4, capacity: int = 64 * 48 * 3 * 2) -> fr.FrameRing:
        ring = fr.FrameRing.create(slots, capacity, prefix=prefix)
        rings.append(ring)
        return ring

    yield _make
    for r in rings:
        r.close()


def dead_pid() -> int:
    """The pid of a process that has exited and been reaped."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait(10)
    return proc.pid


def test_round_trip_is_byte_identical_and_read_only(make_ring: Callable[..., fr.FrameRing]) -> None:
    ring = make_ring()
    writer, reader = fr.RingWriter(ring.name), fr.RingReader(ring.name)
    left = builders.jpeg(builders.image(seed=1))
    right_img = builders.image(seed=2)
    slot = writer.acquire()
    assert slot is not None
    ref = writer.write(slot, left, right_img)
    assert ref.generation % 2 == 0 and ref.generation >= 2
    assert ref.right_offset % fr.ALIGN == 0
    lv, rv = reader.view(ref)
    assert lv.tobytes() == left
    assert rv.tobytes() == right_img.tobytes()
    assert np.array_equal(rv.reshape(right_img.shape), right_img)
    assert not lv.flags.writeable and not rv.flags.writeable
    # Zero-copy: the view's memory lies inside the reader's mapping.
    assert lv.base is not None and not lv.flags.owndata
    reader.check(ref)
    assert reader.rejected == 0
    assert frame_msgs.decode_frame_ref(messages.encode(ref)) == ref
    del lv, rv
    reader.close()
    writer.close()


def test_acquire_returns_none_when_full_and_counts(make_ring: Callable[..., fr.FrameRing]) -> None:
    ring = make_ring(slots=3)
    writer = fr.RingWriter(ring.name)
    refs = []
    for _ in range(3):
        slot = writer.acquire()
        assert slot is not None
        refs.append(writer.write(slot, b"l", b"r"))
    assert writer.acquire() is None
    assert writer.acquire() is None
    assert writer.full == 2
    assert ring.counts() == {"free": 0, "writing": 0, "held": 3}
    assert ring.free_ref(refs[1])
    assert writer.acquire() == refs[1].slot
    writer.close()


def test_free_is_idempotent_and_checks_generation(make_ring: Callable[..., fr.FrameRing]) -> None:
    ring = make_ring(slots=1)
    writer = fr.RingWriter(ring.name)
    slot = writer.acquire()
    assert slot is not None
    old = writer.write(slot, b"a", b"b")
    assert ring.free_ref(old)
    assert not ring.free_ref(old)  # second free of the same pair: no effect
    slot = writer.acquire()
    assert slot is not None
    new = writer.write(slot, b"c", b"d")
    assert not ring.free_ref(old)  # a late free of the old pair must not free the new one
    assert ring.state(slot) == fr.HELD
    assert ring.free_ref(new)
    writer.close()


def test_round_robin_reuses_the_longest_free_slot(make_ring: Callable[..., fr.FrameRing]) -> None:
    ring = make_ring(slots=3)
    writer = fr.RingWriter(ring.name)
    order = []
    for _ in range(6):
        slot = writer.acquire()
        assert slot is not None
        order.append(slot)
        ring.free_ref(writer.write(slot, b"x", b"y"))
    assert order == [0, 1, 2, 0, 1, 2]
    writer.close()


def test_reuse_is_detected_before_and_after_the_read(
        make_ring: Callable[..., fr.FrameRing]) -> None:
    ring = make_ring(slots=1)
    writer, reader = fr.RingWriter(ring.name), fr.RingReader(ring.name)
    slot = writer.acquire()
    assert slot is not None
    ref = writer.write(slot, b"old-left", b"old-right")
    lv, _ = reader.view(ref)
    ring.free_ref(ref)  # the owner frees it while the reader still uses it
    slot = writer.acquire()
    assert slot is not None
    writer.write(slot, b"new-left", b"new-right")
    assert lv.tobytes() == b"new-left"  # what a silent reader would have used
    with pytest.raises(fr.StaleFrame, match="after the read"):
        reader.check(ref)
    with pytest.raises(fr.StaleFrame, match="before the read"):
        reader.view(ref)
    with pytest.raises(fr.StaleFrame), reader.pair(ref):
        pass
    assert reader.rejected == 3
    del lv
    reader.close()
    writer.close()


def test_pair_context_checks_on_exit(make_ring: Callable[..., fr.FrameRing]) -> None:
    ring = make_ring(slots=1)
    writer, reader = fr.RingWriter(ring.name), fr.RingReader(ring.name)
    slot = writer.acquire()
    assert slot is not None
    ref = writer.write(slot, b"L", b"R")
    with pytest.raises(fr.StaleFrame), reader.pair(ref) as (left, right):
        assert (left.tobytes(), right.tobytes()) == (b"L", b"R")
        ring.free_ref(ref)
        writer.write(writer.acquire(), b"X", b"Y")  # type: ignore[arg-type]
    assert reader.rejected == 1
    del left, right
    reader.close()
    writer.close()


@pytest.mark.parametrize("n_left, n_right, error", [
    (0, 1, "expected 1..18432 payload bytes per pair, got 0 \\+ 1"),
    (1, 0, "expected 1.."),
    (64 * 48 * 3 * 2, 1, "expected 1.."),
    (64 * 48 * 3 + 1, 64 * 48 * 3, "expected 1.."),
    (64 * 48 * 3, 64 * 48 * 3, None),
    (1, 1, None),
])
def test_write_bounds(make_ring: Callable[..., fr.FrameRing], n_left: int, n_right: int,
                      error: str | None) -> None:
    left, right = bytes(n_left), bytes(n_right)
    ring = make_ring(slots=1, capacity=64 * 48 * 3 * 2)
    writer = fr.RingWriter(ring.name)
    slot = writer.acquire()
    assert slot is not None
    if error is None:
        writer.write(slot, left, right)
    else:
        with pytest.raises(fr.RingError, match=error):
            writer.write(slot, left, right)
        writer.release(slot)
        assert ring.counts()["free"] == 1
    writer.close()


def test_a_pair_made_in_place_reads_as_a_written_one(
        make_ring: Callable[..., fr.FrameRing]) -> None:
    """begin() hands out the slot's own memory and commit() publishes it: the reader sees
    the bytes the producer put there, and the same descriptor write() gives for them."""
    ring = make_ring(slots=2)
    writer, reader = fr.RingWriter(ring.name), fr.RingReader(ring.name)
    img = builders.image(seed=3)
    slot = writer.acquire()
    assert slot is not None
    lv, rv = writer.begin(slot, img.nbytes, 5)
    lv.reshape(img.shape)[:] = img  # a decoder writing its output straight into the slot
    rv[:] = np.frombuffer(b"right", np.uint8)
    assert ring.generation(slot) % 2 == 1  # odd while it is being made: no reader trusts it
    ref = writer.commit(slot)
    left, right = reader.view(ref)
    assert np.array_equal(left.reshape(img.shape), img) and right.tobytes() == b"right"
    slot2 = writer.acquire()
    assert slot2 is not None
    assert writer.write(slot2, img, b"right").right_offset == ref.right_offset
    assert ring.state(slot) == fr.HELD and ref.generation % 2 == 0
    del left, right, lv, rv
    reader.close()
    writer.close()


@pytest.mark.parametrize("opened", [False, True])
def test_commit_needs_a_slot_opened_by_begin(make_ring: Callable[..., fr.FrameRing],
                                             opened: bool) -> None:
    ring = make_ring(slots=1)
    writer = fr.RingWriter(ring.name)
    slot = writer.acquire()
    assert slot is not None
    if opened:  # opened, committed: a second commit is refused
        writer.begin(slot, 1, 1)
        writer.commit(slot)
    with pytest.raises(fr.RingError, match="opened by begin"):
        writer.commit(slot)
    writer.close()


def test_write_needs_an_acquired_slot(make_ring: Callable[..., fr.FrameRing]) -> None:
    ring = make_ring(slots=2)
    writer = fr.RingWriter(ring.name)
    for slot in (0, 5, -1):
        with pytest.raises(fr.RingError, match="acquired slot"):
            writer.write(slot, b"l", b"r")
    writer.close()


def test_new_writer_reclaims_slots_a_crashed_writer_left(
        make_ring: Callable[..., fr.FrameRing]) -> None:
    ring = make_ring(slots=3)
    crashed = fr.RingWriter(ring.name)
    held = crashed.write(crashed.acquire(), b"l", b"r")  # type: ignore[arg-type]
    stuck = crashed.acquire()
    assert stuck is not None
    crashed._words[stuck, 0] += 1  # died between the odd and the even generation
    crashed.close()
    writer = fr.RingWriter(ring.name)
    assert ring.counts() == {"free": 2, "writing": 0, "held": 1}
    assert ring.generation(stuck) % 2 == 0
    ref = writer.write(writer.acquire(), b"a", b"b")  # type: ignore[arg-type]
    assert ref.generation % 2 == 0
    assert ring.free_ref(held)
    writer.close()


def ref(**kw: object) -> frame_msgs.FrameRef:
    fields: dict[str, object] = dict(segment="seg", slot=0, generation=2, left_offset=64,
                                     left_length=100, right_offset=192, right_length=100)
    fields.update(kw)
    return frame_msgs.FrameRef(**fields)  # type: ignore[arg-type]


SLOTS, SLOT_SIZE = 4, 4096


@pytest.mark.parametrize("bad, error", [
    ({}, None),
    ({"slot": 3}, None),
    ({"slot": 4}, "expected slot in 0..3, got 4"),
    ({"slot": 1 << 40}, "expected slot in 0..3"),
    ({"generation": 0}, "even committed generation >= 2, got 0"),
    ({"generation": 3}, "even committed generation >= 2, got 3"),
    ({"left_offset": 0}, "left bytes within 64..4096"),
    ({"left_offset": 63}, "left bytes within 64..4096"),
    ({"right_offset": 4000}, "right bytes within 64..4096, got offset 4000 length 100"),
    ({"right_length": 1 << 62}, "right bytes within"),
    ({"left_length": 0}, "left length >= 1, got 0"),
    ({"right_offset": 100}, "disjoint left and right"),
    ({"right_offset": 64, "left_offset": 64}, "disjoint"),
])
def test_check_frame_ref(bad: dict[str, int], error: str | None) -> None:
    r = ref(**bad)
    if error is None:
        frame_msgs.check_frame_ref(r, SLOTS, SLOT_SIZE)
    else:
        with pytest.raises(ProtocolError, match=error):
            frame_msgs.check_frame_ref(r, SLOTS, SLOT_SIZE)


@pytest.mark.parametrize("data, error", [
    (messages.encode(ref()), None),
    (msgspec.msgpack.encode({"type": "frameref", "segment": "s", "slot": -1, "generation": 2,
                             "left_offset": 64, "left_length": 1, "right_offset": 128,
                             "right_length": 1}), "Expected `int` >= 0"),
    (msgspec.msgpack.encode({"type": "frameref", "segment": "", "slot": 0, "generation": 2,
                             "left_offset": 64, "left_length": 1, "right_offset": 128,
                             "right_length": 1}), "length >= 1"),
    (msgspec.msgpack.encode({"type": "pair"}), "Invalid value 'pair'"),
    (b"\xc1", "invalid"),
    (bytes(5000), "expected at most 4096 bytes"),
])
def test_decode_frame_ref(data: bytes, error: str | None) -> None:
    if error is None:
        assert frame_msgs.decode_frame_ref(data) == ref()
    else:
        with pytest.raises(ProtocolError, match=error):
            frame_msgs.decode_frame_ref(data)


def test_reader_rejects_hostile_descriptors(make_ring: Callable[..., fr.FrameRing]) -> None:
    ring = make_ring(slots=2)
    reader = fr.RingReader(ring.name)
    cases = [
        (ref(segment="trapflow-1-other"), "expected segment"),
        (ref(segment=ring.name, slot=2), "expected slot in 0..1"),
        (ref(segment=ring.name, right_offset=ring.slot_size - 10), "right bytes within"),
    ]
    for bad, error in cases:
        with pytest.raises(ProtocolError, match=error):
            reader.view(bad)
    # A well-formed descriptor of a slot never written is stale, not garbage.
    with pytest.raises(fr.StaleFrame):
        reader.view(ref(segment=ring.name))
    reader.close()


@pytest.mark.parametrize("content, error", [
    (None, "No such file|cannot open"),
    (b"", "expected a header"),
    (b"NOTARING" + bytes(200), "expected magic"),
])
def test_attach_rejects_what_is_not_a_ring(prefix: str, content: bytes | None,
                                           error: str) -> None:
    name = f"{prefix}{os.getpid()}-bad"
    if content is not None:
        with open(os.path.join(fr.SHM_DIR, name), "wb") as f:
            f.write(content)
    with pytest.raises(fr.RingError, match=error):
        fr.RingReader(name)


def test_close_unlinks_only_for_the_creator(make_ring: Callable[..., fr.FrameRing],
                                            prefix: str) -> None:
    ring = make_ring()
    reader = fr.RingReader(ring.name)
    reader.close()
    assert fr.list_segments(prefix) == [ring.name]
    ring.close()
    assert fr.list_segments(prefix) == []


def test_cleanup_removes_only_segments_of_dead_owners(prefix: str) -> None:
    live = fr.FrameRing.create(1, 16, prefix=prefix)
    dead = fr.FrameRing.create(1, 16, prefix=prefix, owner_pid=dead_pid())
    dead._owner = False  # as if its owner was killed: nobody unlinks it
    dead.close()
    recycled = fr.FrameRing.create(1, 16, prefix=prefix)
    recycled._owner = False
    recycled.close()
    # The owner pid is alive but belongs to a newer process than the one that created it.
    with open(os.path.join(fr.SHM_DIR, recycled.name), "r+b") as f:
        f.seek(40)
        f.write((1).to_bytes(8, "little"))
    foreign = f"{prefix}notapid-x"
    open(os.path.join(fr.SHM_DIR, foreign), "wb").close()
    removed = fr.cleanup_stale(prefix)
    assert sorted(removed) == sorted([dead.name, recycled.name])
    assert fr.list_segments(prefix) == sorted([live.name, foreign])
    live.close()


def test_sizing_from_config() -> None:
    cfg = configmod.from_data({"pools": only_pools({
        "mono": {"count": 2, "credit": 2, "policy": "latest"},
        "vo": {"count": 1, "policy": "ordered:16"},
        "scallop": {"count": 1, "policy": "fifo:4"},
    })})
    # mono 2x2 + 1, vo 1 + 16, scallop 1 + 4, pre-roll 30, in transit 9 (running pools only,
    # as the supervisor counts them)
    running = [p for p in cfg.pools.values() if p.count > 0]
    assert fr.ring_slots(running, preroll=30) == 5 + 17 + 5 + 30 + 9
    assert fr.slot_capacity(1280, 720) == 5_529_600


@pytest.mark.parametrize("data, error", [
    ({}, None),
    ({"transport": "shm", "spare_slots": 4, "preroll_slots": 30}, None),
    ({"transport": "udp"}, "Invalid enum value 'udp'"),
    ({"spare_slots": -1}, ">= 0"),
    ({"slots": 4}, "unknown field"),
])
def test_frames_config(data: dict[str, object], error: str | None) -> None:
    if error is None:
        msgspec.convert(data, fr.FramesConfig)
    else:
        with pytest.raises(msgspec.ValidationError, match=error):
            msgspec.convert(data, fr.FramesConfig)


# --- cleanup across pid namespaces (issue 14 leftovers) ------------------------------------

NS, BOOT = 4026531836, "0123456789abcdef"
OWNER = fr.SegmentOwner(pid=1234, pidns=NS, boot=BOOT)


@pytest.mark.parametrize(("owner", "live_start", "header_start", "remove", "why"), [
    (OWNER, None, None, True, "is gone"),  # pid dead here: ours and dead
    (OWNER, None, 77, True, "is gone"),
    (OWNER, 77, 77, False, "is alive"),
    (OWNER, 78, 77, True, "newer process"),  # pid reused by another process
    (OWNER, 78, 0, False, "is alive"),  # no start time recorded: cannot tell reuse
    (OWNER, 77, None, False, "being created"),
    # Another container sharing /dev/shm: its pid says nothing here, dead or alive.
    (fr.SegmentOwner(1234, NS + 1, BOOT), None, 77, False, "another pid namespace"),
    (fr.SegmentOwner(1234, NS + 1, BOOT), 77, 77, False, "another pid namespace"),
    # A previous boot: nothing of it runs now, whatever the namespace.
    (fr.SegmentOwner(1234, NS + 1, "feedfacefeedface"), 77, 77, True, "before this boot"),
    (fr.SegmentOwner(1234, NS, "feedfacefeedface"), None, None, True, "before this boot"),
    (None, None, None, False, "does not say"),  # legacy or foreign name
])
def test_stale_verdict_removes_only_provably_ours_and_dead(
        owner: fr.SegmentOwner | None, live_start: int | None, header_start: int | None,
        remove: bool, why: str) -> None:
    """Pins cleanup_stale deciding by pid alone: across pid namespaces (containers sharing
    /dev/shm) a live owner's segment was removed under it, as its pid is dead here."""
    got, reason = fr.stale_verdict(owner, NS, BOOT, live_start, header_start)
    assert got is remove and why in reason


@pytest.mark.parametrize(("name", "owner"), [
    ("trapflow-12-4026531836-0123456789abcdef-a1b2c3d4",
     fr.SegmentOwner(12, 4026531836, "0123456789abcdef")),
    ("trapflow-12-a1b2c3d4", None),  # named before segments said their namespace
    ("trapflow-x-4026531836-0123-a1b2", None),
    ("trapflow-12-ns-0123-a1b2", None),
    ("other-12-4026531836-0123-a1b2", None),
])
def test_owner_of_reads_the_name(name: str, owner: fr.SegmentOwner | None) -> None:
    assert fr.owner_of(name) == owner


def test_new_segments_name_this_namespace_and_boot(prefix: str) -> None:
    ring = fr.FrameRing.create(1, 16, prefix=prefix)
    try:
        assert fr.owner_of(ring.name, prefix) == fr.SegmentOwner(
            os.getpid(), fr.own_pidns(), fr.boot_id())
        assert fr.own_pidns() > 0 and len(fr.boot_id()) == 16
    finally:
        ring.close()


def test_cleanup_leaves_other_namespaces_and_removes_previous_boots(prefix: str) -> None:
    other_ns = f"{prefix}{dead_pid()}-{fr.own_pidns() + 1}-{fr.boot_id()}-aaaa0001"
    old_boot = f"{prefix}{os.getpid()}-{fr.own_pidns()}-feedfacefeedface-aaaa0002"
    legacy = f"{prefix}{dead_pid()}-aaaa0003"
    for name in (other_ns, old_boot, legacy):
        open(os.path.join(fr.SHM_DIR, name), "wb").close()
    assert fr.cleanup_stale(prefix) == [old_boot]
    assert fr.list_segments(prefix) == sorted([other_ns, legacy])
