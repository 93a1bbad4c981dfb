"""Thumbnails over the modem, pure: a crop fitted to a byte budget as a baseline JPEG
whose header is left out (both ends make it from the same few numbers), in packets that
each decode on their own.

The box encodes the crop with the standard tables (no optimised Huffman tables: those
would have to travel) and a restart marker every `interval` MCUs, so the entropy-coded
data falls into segments that each start afresh (the DC predictors reset). A packet
carries whole consecutive segments and says which one it starts at, the thumbnail's size
and quality; the surface rebuilds the header by encoding a blank image with the same
numbers, fills the segments of a lost packet with a flat grey segment, and decodes. So a
lost packet costs its rows of the picture, never the picture.

Fitting: the largest of SIDES (the crop's longest side, in pixels) whose encoding fits the
budget at QUALITY_FLOOR or better, at the best quality that fits; when none does, the
smallest side at the best quality that fits, or nothing. Which codec, sizes and qualities:
the table of docs/review.md (`scripts/measure_thumbs.py`).
"""

from __future__ import annotations

import base64
import binascii
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

# Longest sides tried, largest first, and qualities tried, best first.
SIDES = (96, 80, 64, 56, 48, 40, 32, 24)
QUALITIES = (90, 75, 60, 50, 40, 30, 25, 20, 15, 10)
QUALITY_FLOOR = 25
# Bytes a packet's fields other than its segments take in its link record (kind, field
# mask, track, start segment, width, height, quality, shape, data length: one byte each,
# two for a track id from 128 to 16383; counted against the budget), and the most segment
# bytes one packet carries by default: its record then fits the 80-byte message body of a
# default DATA frame (modem.max_frame_payload 96; max_packet() for another).
PACKET_OVERHEAD = 10
MAX_PACKET = 70
# The outbox record of one packet (its class: the message class `thumb`).
RECORD = "thumb"
_SOS, _EOI = b"\xff\xda", b"\xff\xd9"


@dataclass(frozen=True)
class Packet:
    """One part of a thumbnail: the segments from `first` on, as the JPEG has them (with
    the restart markers between them), and what the surface needs to rebuild the header."""

    first: int
    width: int
    height: int
    quality: int
    colour: bool
    interval: int  # MCUs per segment
    data: bytes

    def cost(self) -> int:
        """Bytes it takes in the outbox, about."""
        return len(self.data) + PACKET_OVERHEAD


def _params(quality: int, interval: int) -> list[int]:
    return [cv2.IMWRITE_JPEG_QUALITY, quality, cv2.IMWRITE_JPEG_OPTIMIZE, 0,
            cv2.IMWRITE_JPEG_PROGRESSIVE, 0, cv2.IMWRITE_JPEG_RST_INTERVAL, interval]


def _mcu(colour: bool) -> int:
    return 16 if colour else 8  # 4:2:0 colour, or grey


def _encode(img: np.ndarray, quality: int, interval: int) -> bytes:
    ok, buf = cv2.imencode(".jpg", img, _params(quality, interval))
    if not ok:
        raise ValueError("thumbnail: the JPEG encoder refused the image")
    return buf.tobytes()


def _split(jpeg: bytes) -> tuple[bytes, list[bytes]]:
    """A baseline JPEG's header (through the start-of-scan segment) and its entropy-coded
    segments (between restart markers)."""
    sos = jpeg.index(_SOS)
    end = sos + 2 + int.from_bytes(jpeg[sos + 2:sos + 4], "big")
    body = jpeg[end:]
    if body.endswith(_EOI):
        body = body[:-2]
    segs: list[bytes] = []
    start = i = 0
    while i < len(body) - 1:
        if body[i] == 0xFF and 0xD0 <= body[i + 1] <= 0xD7:
            segs.append(body[start:i])
            start = i = i + 2
        else:
            i += 1
    segs.append(body[start:])
    return jpeg[:end], segs


def _blank(width: int, height: int, colour: bool) -> np.ndarray:
    shape = (height, width, 3) if colour else (height, width)
    return np.full(shape, 128, np.uint8)


def header(width: int, height: int, quality: int, colour: bool, interval: int) -> bytes:
    """The header both ends make: that of a blank image with the same numbers."""
    return _split(_encode(_blank(width, height, colour), quality, interval))[0]


def filler(width: int, height: int, quality: int, colour: bool, interval: int) -> bytes:
    """A flat grey segment, for a lost one."""
    return _split(_encode(_blank(width, height, colour), quality, interval))[1][0]


def _resize(crop: np.ndarray, side: int, colour: bool) -> np.ndarray:
    img = crop if colour or crop.ndim == 2 else cv2.cvtColor(crop, cv2.COLOR_BGR2GRAY)
    if colour and img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    h, w = img.shape[:2]
    scale = side / max(h, w)
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    return cv2.resize(img, size, interpolation=interp)


def max_packet(max_body: int) -> int:
    """The most segment bytes a packet may carry when a message body may take `max_body`
    bytes (trapflow.modem.frame.max_body)."""
    return max(8, min(MAX_PACKET, max_body - PACKET_OVERHEAD))


def _packets(img: np.ndarray, quality: int, colour: bool,
             most: int = MAX_PACKET) -> list[Packet]:
    """One encoding as packets: a segment per MCU row, halved until each fits `most`."""
    h, w = img.shape[:2]
    interval = -(-w // _mcu(colour))
    while True:
        segs = _split(_encode(img, quality, interval))[1]
        if max(map(len, segs)) <= most - 2 or interval == 1:
            break
        interval = max(1, interval // 2)
    out: list[Packet] = []
    first, run = 0, b""
    for i, seg in enumerate(segs):
        marker = bytes((0xFF, 0xD0 + (i % 8)))
        if run and len(run) + 2 + len(seg) > most:
            out.append(Packet(first, w, h, quality, colour, interval, run))
            first, run = i, b""
        run = seg if not run else run + marker + seg
    out.append(Packet(first, w, h, quality, colour, interval, run))
    return out


def fit(crop: np.ndarray, budget: int, colour: bool = True,
        most: int = MAX_PACKET) -> list[Packet]:
    """A crop (BGR) as the packets of the best thumbnail within `budget` bytes (the sum of
    the packets' cost), each carrying at most `most` segment bytes; [] when not even the
    smallest fits (or a segment is larger than `most`)."""
    fallback: list[Packet] = []
    for side in SIDES:
        img = _resize(crop, side, colour)
        for quality in QUALITIES:
            packets = _packets(img, quality, colour, most)
            if (sum(p.cost() for p in packets) <= budget
                    and max(len(p.data) for p in packets) <= most):
                if quality >= QUALITY_FLOOR:
                    return packets
                if not fallback:
                    fallback = packets
                break
    return fallback


def _segments(packet: Packet) -> list[bytes]:
    return _split(_SOS + b"\x00\x02" + packet.data)[1]


def total_segments(packet: Packet) -> int:
    """How many segments the thumbnail a packet belongs to has (its MCUs over the restart
    interval): any one packet says it."""
    mcu = _mcu(packet.colour)
    mcus = (-(-packet.width // mcu)) * (-(-packet.height // mcu))
    return -(-mcus // packet.interval)


def segment_count(packet: Packet) -> int:
    """How many segments one packet carries."""
    return len(_segments(packet))


def assemble(packets: list[Packet], segments: int | None = None) -> bytes:
    """The JPEG of a thumbnail from the packets that arrived (any subset, any order, all of
    one thumbnail): the header rebuilt, a lost packet's segments flat grey. `segments`: how
    many the thumbnail has, when known (else up to the last one heard)."""
    if not packets:
        raise ValueError("thumbnail: no packet")
    p0 = packets[0]
    key = (p0.width, p0.height, p0.quality, p0.colour, p0.interval)
    got: dict[int, bytes] = {}
    for p in packets:
        if (p.width, p.height, p.quality, p.colour, p.interval) != key:
            raise ValueError("thumbnail: packets of different thumbnails")
        for i, seg in enumerate(_segments(p)):
            got[p.first + i] = seg
    total = segments if segments is not None else total_segments(p0)
    flat = filler(*key) if len(got) < total else b""
    body = bytearray(header(*key))
    for i in range(total):
        if i:
            body += bytes((0xFF, 0xD0 + ((i - 1) % 8)))
        body += got.get(i, flat)
    return bytes(body + _EOI)


def decode(packets: list[Packet]) -> np.ndarray:
    """The thumbnail's pixels (BGR, or grey) from the packets that arrived."""
    data = np.frombuffer(assemble(packets), np.uint8)
    flags = cv2.IMREAD_COLOR if packets[0].colour else cv2.IMREAD_GRAYSCALE
    img = cv2.imdecode(data, flags)
    if img is None:
        raise ValueError("thumbnail: the packets do not decode")
    return img


def record(track: int, packet: Packet) -> dict[str, Any]:
    """One packet as an outbox record (JSON: the segments in base64), for the link codec's
    `thumb` kind; `shape` is the restart interval and the colour flag in one number."""
    return {RECORD: {"track": track, "first": packet.first, "width": packet.width,
                     "height": packet.height, "quality": packet.quality,
                     "shape": packet.interval * 2 + int(packet.colour),
                     "data": base64.b64encode(packet.data).decode()}}


def records(track: int, jpeg: bytes, budget: int,
            most: int = MAX_PACKET) -> list[dict[str, Any]]:
    """A queued track's crop (a JPEG) as the outbox records of its thumbnail within
    `budget` bytes, each packet at most `most` segment bytes (max_packet); [] when the
    crop does not decode or no thumbnail fits."""
    crop = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    packets = fit(crop, budget, True, most) if crop is not None and crop.size else []
    return [record(track, p) for p in packets]


def cost(recs: list[dict[str, Any]]) -> int:
    """What a thumbnail's records take against its budget (Packet.cost summed)."""
    return sum(from_record(r[RECORD])[1].cost() for r in recs)


def from_record(body: dict[str, Any]) -> tuple[int, Packet]:
    """A `thumb` record's body back as (track, packet); ValueError when it is none."""
    try:
        shape = int(body["shape"])
        packet = Packet(int(body["first"]), int(body["width"]), int(body["height"]),
                        int(body["quality"]), bool(shape & 1), shape >> 1,
                        base64.b64decode(body["data"], validate=True))
        track = int(body["track"])
    except (KeyError, TypeError, ValueError, binascii.Error) as exc:
        raise ValueError(f"thumbnail: not a packet record: {exc}") from None
    if not (0 < packet.width <= 1024 and 0 < packet.height <= 1024 and packet.interval > 0
            and 1 <= packet.quality <= 100 and packet.first >= 0):
        raise ValueError(f"thumbnail: packet out of range: {packet.width}x{packet.height} "
                         f"q{packet.quality} interval {packet.interval}")
    return track, packet
