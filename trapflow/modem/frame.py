"""Byte framing on the modem link: sync, length, type, payload, CRC-16; and the ARQ payloads.

The one module (with link_codec) that knows the link's byte format. A frame is
`A5 5A | len | type | payload[len] | crc16` with the CRC (CCITT) over len, type and
payload. The deframer resynchronises on garbage, counts what it throws away, and
never raises on bad input.

Both ARQ payloads start with the 4-byte session id of the outbox the records come
from (created with the outbox, kept in it): message ids are the outbox's seqs, which a
fresh outbox numbers from 1 again, so the surface keeps its de-duplication per session
and the sender takes only acknowledgements of its own session. Link protocol 1 (types
1 and 2, without a session) is still recognised, so that it can be refused by name.

COMMAND (surface -> box) and REPLY (box -> surface) carry signed operator commands: the
box's outbox session, a counter, the command or the reply, and a truncated HMAC-SHA256 tag
over the frame type and everything before the tag (trapflow.modem.command checks it).
Frame types are append only: a receiver that does not know one drops it as garbage.
"""

from __future__ import annotations

import binascii
import struct
from collections.abc import Iterable
from dataclasses import dataclass

from trapflow.config.modem import MAX_PAYLOAD
from trapflow.errors import ProtocolError

SYNC = b"\xa5\x5a"
HEADER = len(SYNC) + 2  # sync, len, type
OVERHEAD = HEADER + 2  # plus the CRC

LEGACY_DATA = 0x01  # link protocol 1, no session: refused and counted, never acknowledged
LEGACY_ACK = 0x02  # link protocol 1, no session: ignored by the sender
DATA = 0x03  # box -> surface: session, floor, then (msg id, body) pairs
ACK = 0x04  # surface -> box: session, message ids received
COMMAND = 0x05  # surface -> box: session, counter, command, tag
REPLY = 0x06  # box -> surface: session, counter, status, body, tag
LEGACY_TYPES = (LEGACY_DATA, LEGACY_ACK)
FRAME_TYPES = (DATA, ACK, COMMAND, REPLY, *LEGACY_TYPES)

SESSION_BYTES = 4
"""Size of an outbox's session id. One in 2**32 fresh outboxes collides with the one
before (and its records would be taken for retransmissions); 4 bytes are 4 % of a full
DATA frame at the default 96-byte payload."""


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE."""
    return binascii.crc_hqx(data, 0xFFFF)


def frame(kind: int, payload: bytes) -> bytes:
    """One frame on the wire."""
    if kind not in FRAME_TYPES:
        raise ProtocolError(f"expected a frame type in {FRAME_TYPES}, got {kind}")
    if len(payload) > MAX_PAYLOAD:
        raise ProtocolError(
            f"expected a payload of at most {MAX_PAYLOAD} bytes, got {len(payload)}"
        )
    body = bytes((len(payload), kind)) + payload
    return SYNC + body + crc16(body).to_bytes(2, "big")


class Deframer:
    """Turns a byte stream into (type, payload) frames; garbage is dropped and counted."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.frames = 0
        self.garbage_bytes = 0
        self.crc_errors = 0

    def feed(self, data: bytes) -> list[tuple[int, bytes]]:
        """Add bytes; returns the complete, valid frames they finish."""
        self._buf += data
        out: list[tuple[int, bytes]] = []
        buf = self._buf
        while True:
            start = buf.find(SYNC)
            if start < 0:
                # Keep a trailing first sync byte: the next read may complete the marker.
                keep = 1 if buf.endswith(SYNC[:1]) else 0
                self.garbage_bytes += len(buf) - keep
                del buf[: len(buf) - keep]
                break
            if start:
                self.garbage_bytes += start
                del buf[:start]
            if len(buf) < HEADER:
                break
            size = buf[2]
            end = HEADER + size + 2
            if len(buf) < end:
                break
            body = bytes(buf[2 : HEADER + size])
            crc = int.from_bytes(buf[HEADER + size : end], "big")
            if crc != crc16(body) or body[1] not in FRAME_TYPES:
                # A false or damaged sync: skip one byte and look for the next marker.
                self.crc_errors += 1
                self.garbage_bytes += 1
                del buf[:1]
                continue
            del buf[:end]
            self.frames += 1
            out.append((body[1], body[2:]))
        return out

    def stats(self) -> dict[str, int]:
        """Counters for the stats topic."""
        return {
            "frames": self.frames,
            "garbage_bytes": self.garbage_bytes,
            "crc_errors": self.crc_errors,
        }


def split_packets(buf: bytearray) -> list[bytes]:
    """Cut complete frame-shaped packets (unchecked) and loose garbage off the front of buf.

    The simulator uses this to drop or damage whole packets as an acoustic modem does;
    an incomplete frame is left in buf for the next read.
    """
    out: list[bytes] = []
    while buf:
        start = buf.find(SYNC)
        if start < 0:
            keep = 1 if buf.endswith(SYNC[:1]) else 0
            if len(buf) > keep:
                out.append(bytes(buf[: len(buf) - keep]))
                del buf[: len(buf) - keep]
            break
        if start:
            out.append(bytes(buf[:start]))
            del buf[:start]
        if len(buf) < HEADER:
            break
        end = HEADER + buf[2] + 2
        if len(buf) < end:
            break
        out.append(bytes(buf[:end]))
        del buf[:end]
    return out


# --- varints ------------------------------------------------------------------


def put_uvarint(out: bytearray, value: int) -> None:
    """Append an unsigned LEB128 varint."""
    if value < 0:
        raise ProtocolError(f"expected an unsigned integer, got {value}")
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)


def put_svarint(out: bytearray, value: int) -> None:
    """Append a zigzag-encoded signed varint."""
    put_uvarint(out, value * 2 if value >= 0 else -value * 2 - 1)


class Reader:
    """Reads varints and bytes from a payload; ProtocolError when it runs short."""

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.pos = 0

    def done(self) -> bool:
        """True when every byte has been read."""
        return self.pos >= len(self.data)

    def uvarint(self) -> int:
        """Read an unsigned varint."""
        shift = value = 0
        while True:
            if self.pos >= len(self.data):
                raise ProtocolError(f"expected a varint at byte {self.pos}, got the end of data")
            byte = self.data[self.pos]
            self.pos += 1
            value |= (byte & 0x7F) << shift
            if byte < 0x80:
                return value
            shift += 7
            if shift > 63:
                raise ProtocolError(f"expected a varint of at most 9 bytes at byte {self.pos}")

    def svarint(self) -> int:
        """Read a zigzag-encoded signed varint."""
        raw = self.uvarint()
        return (raw >> 1) ^ -(raw & 1)

    def take(self, n: int) -> bytes:
        """Read n raw bytes."""
        if self.pos + n > len(self.data):
            raise ProtocolError(
                f"expected {n} bytes at byte {self.pos}, got {len(self.data) - self.pos}"
            )
        chunk = self.data[self.pos : self.pos + n]
        self.pos += n
        return chunk


# --- ARQ payloads -----------------------------------------------------------------


def _check_session(session: bytes) -> None:
    if len(session) != SESSION_BYTES:
        raise ProtocolError(f"expected a session id of {SESSION_BYTES} bytes, got {len(session)}")


def data_payload(session: bytes, floor: int, messages: Iterable[tuple[int, bytes]]) -> bytes:
    """DATA: the outbox's session id, the sender's floor (every id below it is settled),
    then (id, body) pairs."""
    _check_session(session)
    out = bytearray(session)
    put_uvarint(out, floor)
    for msg_id, body in messages:
        put_uvarint(out, msg_id - floor)
        put_uvarint(out, len(body))
        out += body
    return bytes(out)


def max_body(max_frame_payload: int) -> int:
    """The largest message body a DATA payload of `max_frame_payload` bytes is sure to
    carry: the worst case around it is the session, the floor and the id delta (5 bytes
    each) and the body's length."""
    return max_frame_payload - 12 - SESSION_BYTES


def message_cost(floor: int, msg_id: int, body: bytes) -> int:
    """Bytes one message adds to a DATA payload."""
    out = bytearray()
    put_uvarint(out, msg_id - floor)
    put_uvarint(out, len(body))
    return len(out) + len(body)


def parse_data(payload: bytes) -> tuple[bytes, int, list[tuple[int, bytes]]]:
    """Inverse of data_payload: (session, floor, messages); ProtocolError when malformed."""
    r = Reader(payload)
    session = r.take(SESSION_BYTES)
    floor = r.uvarint()
    messages = []
    while not r.done():
        msg_id = floor + r.uvarint()
        messages.append((msg_id, r.take(r.uvarint())))
    return session, floor, messages


def ack_payload(session: bytes, ids: Iterable[int]) -> bytes:
    """ACK: the session id the acknowledged DATA carried, then its message ids, sorted and
    delta-coded."""
    _check_session(session)
    out = bytearray(session)
    prev = 0
    for msg_id in sorted(set(ids)):
        put_uvarint(out, msg_id - prev)
        prev = msg_id
    return bytes(out)


def parse_ack(payload: bytes) -> tuple[bytes, list[int]]:
    """Inverse of ack_payload: (session, ids)."""
    r = Reader(payload)
    session = r.take(SESSION_BYTES)
    ids = []
    prev = 0
    while not r.done():
        prev += r.uvarint()
        ids.append(prev)
    return session, ids


# --- signed commands ----------------------------------------------------------------

TAG_BYTES = 16
"""HMAC-SHA256 tags are cut to their first 16 bytes (RFC 2104 allows truncation to half
the hash). A forger then needs 2**128 tries on average, out of reach on a link of a few
hundred bits per second, while the full 32 bytes would double the cost of a typical
20-byte command on the slowest link."""

# Command kinds (one byte after the counter). Append only: the box must know them all.
CMD_LEVEL = 1  # level name (text), or "auto"
CMD_POOL_COUNT = 2  # pool, count
CMD_POOL_ACTIVATE = 3  # pool
CMD_POOL_DEACTIVATE = 4  # pool
CMD_POOL_POLICY = 5  # pool, policy (text)
CMD_PARAM = 6  # pool, key, value
CMD_STATUS = 7  # a short status now
CMD_HEALTH = 8  # a health record now
CMD_KINDS = {CMD_LEVEL: "level", CMD_POOL_COUNT: "pool_count", CMD_POOL_ACTIVATE: "activate",
             CMD_POOL_DEACTIVATE: "deactivate", CMD_POOL_POLICY: "policy", CMD_PARAM: "param",
             CMD_STATUS: "status", CMD_HEALTH: "health"}  # fmt: skip

# A parameter value: one type byte, then the value.
_V_NONE, _V_FALSE, _V_TRUE, _V_INT, _V_FLOAT, _V_STR = range(6)
MAX_TEXT = 64  # bytes of a name or text argument

# Reply statuses.
REPLY_OK = 0  # executed; body: what changed, the status or the health record
REPLY_ERROR = 1  # executed but the supervisor refused or could not answer; body: why
REPLY_STALE = 2  # counter at or below the last accepted one; body: that counter
REPLY_SESSION = 3  # addressed to another session; the reply carries the box's own
REPLY_BUSY = 4  # another command is still running: send this one again later
REPLY_LOST = 5  # executed before a restart of the box; its reply (or its change) is lost
REPLY_STATUSES = {REPLY_OK: "ok", REPLY_ERROR: "error", REPLY_STALE: "stale",
                  REPLY_SESSION: "session", REPLY_BUSY: "busy", REPLY_LOST: "lost"}  # fmt: skip


@dataclass(frozen=True)
class Command:
    """One operator command as the link carries it (kind is a CMD_* constant)."""

    kind: int
    pool: str = ""
    count: int = 0
    text: str = ""  # the level, the policy, or the parameter's key
    value: str | int | float | bool | None = None  # the parameter's value


@dataclass(frozen=True)
class SignedFrame:
    """A COMMAND or REPLY payload cut into its parts; `signed` is what the tag covers
    (the frame type byte, then the payload up to the tag)."""

    session: bytes
    counter: int
    body: bytes  # the command (kind byte first) or the reply (status byte first)
    tag: bytes
    signed: bytes


def _put_text(out: bytearray, text: str) -> None:
    data = text.encode()
    if len(data) > MAX_TEXT:
        raise ProtocolError(f"expected a name of at most {MAX_TEXT} bytes, got {len(data)}")
    put_uvarint(out, len(data))
    out += data


def _text(r: Reader) -> str:
    n = r.uvarint()
    if n > MAX_TEXT:
        raise ProtocolError(f"expected a name of at most {MAX_TEXT} bytes, got {n}")
    try:
        return r.take(n).decode()
    except UnicodeDecodeError:
        raise ProtocolError("expected UTF-8 text in a command") from None


def command_body(cmd: Command) -> bytes:
    """The command's bytes: kind, then its arguments."""
    if cmd.kind not in CMD_KINDS:
        raise ProtocolError(f"expected a command kind in {sorted(CMD_KINDS)}, got {cmd.kind}")
    out = bytearray((cmd.kind,))
    if cmd.kind == CMD_LEVEL:
        _put_text(out, cmd.text)
    elif cmd.kind in (
        CMD_POOL_COUNT,
        CMD_POOL_ACTIVATE,
        CMD_POOL_DEACTIVATE,
        CMD_POOL_POLICY,
        CMD_PARAM,
    ):
        _put_text(out, cmd.pool)
        if cmd.kind == CMD_POOL_COUNT:
            put_uvarint(out, cmd.count)
        elif cmd.kind in (CMD_POOL_POLICY, CMD_PARAM):
            _put_text(out, cmd.text)
        if cmd.kind == CMD_PARAM:
            _put_value(out, cmd.value)
    return bytes(out)


def _put_value(out: bytearray, v: str | int | float | bool | None) -> None:
    if v is None:
        out.append(_V_NONE)
    elif isinstance(v, bool):
        out.append(_V_TRUE if v else _V_FALSE)
    elif isinstance(v, int):
        out.append(_V_INT)
        put_svarint(out, v)
    elif isinstance(v, float):
        out.append(_V_FLOAT)
        out += struct.pack(">d", v)
    else:
        out.append(_V_STR)
        _put_text(out, v)


def _value(r: Reader) -> str | int | float | bool | None:
    kind = r.take(1)[0]
    if kind == _V_NONE:
        return None
    if kind in (_V_FALSE, _V_TRUE):
        return kind == _V_TRUE
    if kind == _V_INT:
        return r.svarint()
    if kind == _V_FLOAT:
        value: float = struct.unpack(">d", r.take(8))[0]
        return value
    if kind == _V_STR:
        return _text(r)
    raise ProtocolError(f"expected a value type in 0..{_V_STR}, got {kind}")


def parse_command_body(body: bytes) -> Command:
    """Inverse of command_body; ProtocolError for an unknown kind or malformed arguments."""
    r = Reader(body)
    kind = r.take(1)[0]
    if kind not in CMD_KINDS:
        raise ProtocolError(
            f"expected a command kind in {sorted(CMD_KINDS)}, got {kind}: "
            f"update trapflow on the box to the surface's version"
        )
    if kind == CMD_LEVEL:
        cmd = Command(kind, text=_text(r))
    elif kind in (CMD_STATUS, CMD_HEALTH):
        cmd = Command(kind)
    else:
        pool = _text(r)
        if kind == CMD_POOL_COUNT:
            cmd = Command(kind, pool, count=r.uvarint())
        elif kind == CMD_POOL_POLICY:
            cmd = Command(kind, pool, text=_text(r))
        elif kind == CMD_PARAM:
            key = _text(r)
            cmd = Command(kind, pool, text=key, value=_value(r))
        else:
            cmd = Command(kind, pool)
    if not r.done():
        raise ProtocolError(f"expected {r.pos} bytes of {CMD_KINDS[kind]} command, got {len(body)}")
    return cmd


def signed_payload(session: bytes, counter: int, body: bytes) -> bytes:
    """A COMMAND or REPLY payload without its tag: session, counter, body."""
    _check_session(session)
    out = bytearray(session)
    put_uvarint(out, counter)
    return bytes(out + body)


def split_signed(kind: int, payload: bytes) -> SignedFrame:
    """A COMMAND or REPLY payload cut into session, counter, body and tag (unchecked)."""
    if len(payload) < SESSION_BYTES + 1 + 1 + TAG_BYTES:
        raise ProtocolError(
            f"expected a signed payload of at least {SESSION_BYTES + 2 + TAG_BYTES} bytes "
            f"(session, counter, kind, tag), got {len(payload)}"
        )
    head, tag = payload[:-TAG_BYTES], payload[-TAG_BYTES:]
    r = Reader(head)
    session = r.take(SESSION_BYTES)
    counter = r.uvarint()
    body = head[r.pos :]
    if not body:
        raise ProtocolError("expected a command kind or reply status before the tag, got none")
    return SignedFrame(session, counter, body, tag, bytes((kind,)) + head)
