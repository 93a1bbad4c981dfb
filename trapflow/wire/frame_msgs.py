"""Frames by reference on one host: the shared-memory ring's FrameRef descriptor with its
bounds checks, and local-link datagrams that carry several frames in one."""

from __future__ import annotations

import struct
from collections.abc import Sequence
from typing import Annotated

import msgspec

from trapflow.errors import ProtocolError
from trapflow.wire.messages import (
    MAX_HEADER_BYTES,
    MAX_RESULT_BYTES,
    Buffer,
    Msg,
    StereoPair,
    decode_bounded,
    decode_pair_header,
)

# --- shared-memory frames -----------------------------------------------------------
# With a shared-memory ring the pair message is [StereoPair header, FrameRef]: the images
# stay in the ring slot and only this descriptor travels (trapflow/wire/frame_ring.py).

# Bytes at the start of every ring slot before the payload (generation, lengths).
FRAME_SLOT_HEADER = 64
MAX_RING_SLOTS = 4096

_NonNeg = Annotated[int, msgspec.Meta(ge=0)]


class FrameRef(Msg, frozen=True, tag="frameref"):
    """Where one pair lies in a shared-memory ring: slot, its generation when written,
    and the left and right payloads as (offset, length) from the start of the slot."""

    segment: Annotated[str, msgspec.Meta(min_length=1, max_length=200)]
    slot: _NonNeg
    generation: _NonNeg
    left_offset: _NonNeg
    left_length: _NonNeg
    right_offset: _NonNeg
    right_length: _NonNeg


_frame_ref_dec = msgspec.msgpack.Decoder(FrameRef)


def decode_frame_ref(data: Buffer) -> FrameRef:
    """Decode a FrameRef frame (bounds against a ring are checked by check_frame_ref)."""
    ref: FrameRef = decode_bounded(_frame_ref_dec, data, "frame ref", MAX_HEADER_BYTES)
    return ref


def check_frame_ref(ref: FrameRef, ring_slots: int, slot_size: int) -> None:
    """Reject a descriptor that would read outside its slot: ProtocolError with the reason.

    A committed generation is even and at least 2 (odd means a write in progress).
    Both payloads must lie after the slot header, inside the slot, and not overlap.
    """
    what = f"frame ref slot {ref.slot}"
    if not 0 <= ref.slot < ring_slots:
        raise ProtocolError(f"frame ref: expected slot in 0..{ring_slots - 1}, got {ref.slot}")
    if ref.generation < 2 or ref.generation % 2:
        raise ProtocolError(
            f"{what}: expected an even committed generation >= 2, got {ref.generation}")
    spans = []
    for side, off, n in (("left", ref.left_offset, ref.left_length),
                         ("right", ref.right_offset, ref.right_length)):
        if n < 1:
            raise ProtocolError(f"{what}: expected {side} length >= 1, got {n}")
        if off < FRAME_SLOT_HEADER or off + n > slot_size:
            raise ProtocolError(
                f"{what}: expected {side} bytes within {FRAME_SLOT_HEADER}..{slot_size}, "
                f"got offset {off} length {n}")
        spans.append((off, off + n))
    (a0, a1), (b0, b1) = spans
    if a0 < b1 and b0 < a1:
        raise ProtocolError(
            f"{what}: expected disjoint left and right payloads, got left {a0}..{a1} "
            f"and right {b0}..{b1}")


def check_pair_ref(frames: Sequence[Buffer]) -> tuple[StereoPair, FrameRef]:
    """Validate a [header, frame ref] message (images in shared memory)."""
    if len(frames) != 2:
        raise ProtocolError(f"pair: expected 2 frames [header, frame ref], got {len(frames)}")
    pair = decode_pair_header(frames[0])
    return pair, decode_frame_ref(frames[1])


# --- local links: several frames in one datagram ---------------------------------
# On one host, descriptors travel over UNIX seqpacket sockets, one datagram per message.
# A datagram is: u8 frame count, that many u32 little-endian lengths, then the frames.

MAX_LINK_FRAMES = 64  # a batch of results
MAX_LINK_BYTES = MAX_RESULT_BYTES + 2 * MAX_HEADER_BYTES
# The head of a datagram of n frames: its count then n lengths (compiled once per n).
_HEADS = [struct.Struct(f"<B{n}I") for n in range(MAX_LINK_FRAMES + 1)]
_LENGTHS = [struct.Struct(f"<{n}I") for n in range(MAX_LINK_FRAMES + 1)]


def pack_frames(frames: Sequence[Buffer]) -> bytes:
    """One datagram carrying frames (each bytes-like or a zmq.Frame)."""
    bufs = [f.buffer if hasattr(f, "buffer") else f for f in frames]
    if not 0 < len(bufs) <= MAX_LINK_FRAMES:
        raise ProtocolError(f"link message: expected 1..{MAX_LINK_FRAMES} frames, "
                            f"got {len(bufs)}")
    head = _HEADS[len(bufs)].pack(len(bufs), *[memoryview(b).nbytes for b in bufs])
    return b"".join([head, *bufs])


def unpack_frames(data: bytes | memoryview) -> list[memoryview]:
    """The frames of one datagram, as views into it; ProtocolError if it is not one."""
    buf = memoryview(data)
    if buf.nbytes < 1:
        raise ProtocolError("link message: expected a frame count, got an empty datagram")
    n = buf[0]
    at = 1 + 4 * n
    if not 0 < n <= MAX_LINK_FRAMES or buf.nbytes < at:
        raise ProtocolError(f"link message: expected 1..{MAX_LINK_FRAMES} frames and their "
                            f"lengths, got count {n} in {buf.nbytes} bytes")
    frames = []
    for size in _LENGTHS[n].unpack_from(buf, 1):
        frames.append(buf[at:at + size])
        at += size
    if at != buf.nbytes:
        raise ProtocolError(f"link message: frame lengths add up to {at} bytes, "
                            f"datagram has {buf.nbytes}")
    return frames
