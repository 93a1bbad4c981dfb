"""The tap's wire form: its topics, the typed messages a subscriber gets, and decode_tap(),
the one place that knows how each topic is laid out."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Union

import msgspec

from trapflow.errors import ProtocolError
from trapflow.wire.messages import (
    Buffer,
    Stats,
    StereoPair,
    Truth,
    check_pair_frames,
    decode_pair_header,
    decode_result_line,
    decode_stats,
    decode_truth,
)

# A preview image is at most 640 pixels wide: a few tens of kB; far more is no preview.
MAX_PREVIEW_BYTES = 4 << 20

# Tap topics: the first frame of every tap message.
TOPIC_META = b"meta"  # [topic, pair header]
TOPIC_IMAGE = b"image"  # [topic, pair header, left, right]
TOPIC_STATS = b"stats"  # [topic, Stats]
TOPIC_RESULT = b"result"  # [topic, JSON line] (published by the normalizer)
TOPIC_TRUTH = b"truth"  # [topic, Truth] (published by capture, synthetic sources only)
# [topic, pair header, left JPEG, right JPEG]: the viewer's preview, small, at the viewer's
# rate and only while a viewer subscribes (it does while a page is open).
TOPIC_PREVIEW = b"preview"
TAP_TOPICS = (TOPIC_META, TOPIC_IMAGE, TOPIC_STATS, TOPIC_RESULT, TOPIC_TRUTH, TOPIC_PREVIEW)


class TapPair(msgspec.Struct, frozen=True):
    """An image message of the broker's tap: the pair's header and its two images (the
    received buffers, not copied)."""

    header: StereoPair
    left: Buffer
    right: Buffer


class TapPreview(msgspec.Struct, frozen=True):
    """A preview message of the broker's tap: the pair's header as captured (its width and
    height are those of the full frame, which boxes refer to) and two JPEG images, reduced
    to at most PREVIEW_WIDTH pixels wide."""

    header: StereoPair
    left: bytes
    right: bytes


class TapMeta(msgspec.Struct, frozen=True):
    """A frame-metadata message of the broker's tap (the header without images)."""

    header: StereoPair


class TapStats(msgspec.Struct, frozen=True):
    """A stats message of the broker's tap."""

    stats: Stats


class TapResult(msgspec.Struct, frozen=True):
    """A line of the normalizer's result tap: its algorithm, fields and the line itself."""

    kind: str
    fields: dict[str, Any]
    line: bytes


class TapTruth(msgspec.Struct, frozen=True):
    """A synthetic source's ground truth, on the broker's tap."""

    truth: Truth


TapMessage = Union[TapPair, TapPreview, TapMeta, TapStats, TapResult, TapTruth]


def _tap_bytes(frame: Buffer) -> bytes:
    data = getattr(frame, "bytes", None)  # a zmq.Frame received with copy=False
    return data if isinstance(data, bytes) else bytes(frame)


def _tap_view(frame: Buffer) -> Buffer:
    return getattr(frame, "buffer", frame)  # a zmq.Frame's memoryview; bytes as they are


def check_jpegs(frames: Sequence[Buffer]) -> tuple[bytes, bytes]:
    """Two preview images: each a JPEG (starts with its SOI marker) of at most
    MAX_PREVIEW_BYTES."""
    out = []
    for side, frame in zip(("left", "right"), frames, strict=True):
        data = _tap_bytes(frame)
        if not 0 < len(data) <= MAX_PREVIEW_BYTES or data[:2] != b"\xff\xd8":
            raise ProtocolError(f"preview: expected the {side} image as JPEG of 1.."
                                f"{MAX_PREVIEW_BYTES} bytes, got {len(data)} bytes "
                                f"starting {data[:2]!r}")
        out.append(data)
    return out[0], out[1]


def decode_tap(frames: Sequence[Buffer]) -> TapMessage:
    """Decode one message of a tap ([topic, ...] as received, bytes or zmq.Frame): the only
    place that knows how each tap topic is laid out."""
    if not frames:
        raise ProtocolError("tap: expected [topic, ...], got an empty message")
    topic = _tap_bytes(frames[0])
    n = len(frames)
    if topic == TOPIC_IMAGE and n == 4:
        return TapPair(check_pair_frames(frames[1:]), _tap_view(frames[2]),
                       _tap_view(frames[3]))
    if topic == TOPIC_PREVIEW and n == 4:
        return TapPreview(decode_pair_header(frames[1]), *check_jpegs(frames[2:]))
    if topic == TOPIC_RESULT and n == 2:
        kind, fields = decode_result_line(frames[1])
        return TapResult(kind, fields, _tap_bytes(frames[1]))
    if topic == TOPIC_STATS and n == 2:
        return TapStats(decode_stats(frames[1]))
    if topic == TOPIC_META and n == 2:
        return TapMeta(decode_pair_header(frames[1]))
    if topic == TOPIC_TRUTH and n == 2:
        return TapTruth(decode_truth(frames[1]))
    raise ProtocolError(f"tap: expected image [topic, header, left, right] (preview alike) or "
                        f"meta, stats, result, truth [topic, body], got topic {topic[:20]!r} with "
                        f"{n} frames")
