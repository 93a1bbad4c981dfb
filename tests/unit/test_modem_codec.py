"""Link framing, ARQ payloads and the compact codec: golden bytes, size budgets, bad input."""

from __future__ import annotations

import math
import random
from typing import Any

import msgspec
import pytest

from tests import builders
from trapflow.errors import ProtocolError
from trapflow.modem.codec import GENERIC, LinkCodec
from trapflow.modem.frame import (
    ACK,
    DATA,
    Deframer,
    Reader,
    ack_payload,
    data_payload,
    frame,
    parse_ack,
    parse_data,
    put_svarint,
    put_uvarint,
    split_packets,
)

TS = "2025-07-07 12:52:43.120"
TH = 0.1
C, S = round(math.cos(TH), 4), round(math.sin(TH), 4)
RT = [[C, -S, 0.0, 0.05], [S, C, 0.0, -0.01], [0.0, 0.0, 1.0, 0.2]]
RECORDS: list[tuple[dict[str, Any], int]] = [  # record, most link bytes allowed
    ({"mono_ir": {"timestamp": TS, "seq": 17, "label": "crab", "confidence": 0.71,
                  "box": [5.4, 7.8, 15.6, 18.1]}}, 20),
    ({"stereo_ir": {"timestamp": TS, "seq": 18, "label": "scallop", "confidence": 0.93}}, 12),
    ({"stereo_ir": {"timestamp": "2025-07-07 12:52:43", "seq": 1, "label": "new thing",
                    "confidence": 0.5}}, 22),
    ({"stereo_vo": {"timestamp": TS, "seq": 19, "ok": True, "Rt": RT, "inliers": 120}}, 24),
    ({"stereo_vo": {"timestamp": TS, "seq": 20, "ok": False}}, 12),
    ({"tags": {"timestamp": TS, "seq": 21, "id": 3,
               "corners": [[100.5, 200.1], [150.2, 200.3], [150.0, 250.7], [100.1, 250.2]],
               "rotation": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
               "translation": [0.1, 0.2, 1.5], "error": 0.4}}, 40),
    ({"health": {"timestamp": TS, "uptime_s": 3600, "cpu_pct": 55.5, "load1": 1.25,
                 "temp_c": 61.2, "mem_pct": 40.1, "disk_free_mb": 20000, "backlog": 12,
                 "link": "active", "pools": {"mono": [4.5, 10], "stereo": [1.0, 200]}}}, 48),
    # the ladder's level rides in the health record (a level change sends one at once)
    ({"health": {"timestamp": TS, "uptime_s": 3600, "cpu_pct": 55.5, "load1": 1.25,
                 "temp_c": 85.0, "mem_pct": 40.1, "disk_free_mb": 20000, "backlog": 12,
                 "link": "active", "pools": {"mono": [4.5, 10], "stereo": [0.2, 200]},
                 "level": "ir_slowed"}}, 58),
    # the power model's figures ride appended (issue 25): 4 more bytes
    ({"health": {"timestamp": TS, "uptime_s": 3600, "cpu_pct": 55.5, "load1": 1.25,
                 "temp_c": 61.2, "mem_pct": 40.1, "disk_free_mb": 20000, "backlog": 12,
                 "link": "active", "pools": {"mono": [4.5, 10], "stereo": [1.0, 200]},
                 "watts": 5.6, "days": 31.2}}, 52),
    # the image-health state and its ratios to the baseline ride appended (issue 33)
    ({"health": {"timestamp": TS, "uptime_s": 3600, "cpu_pct": 55.5, "load1": 1.25,
                 "temp_c": 61.2, "mem_pct": 40.1, "disk_free_mb": 20000, "backlog": 12,
                 "link": "active", "pools": {"mono": [4.5, 10], "stereo": [1.0, 200]},
                 "watts": 5.6, "days": 31.2, "image": "fouled+turbid",
                 "image_ratio": [0.31, 0.55, 0.82]}}, 72),
    ({"aggregate": {"class": "mono_ir/crab", "from": TS, "to": "2025-07-07 12:53:42.999",
                    "count": 57, "best": [{"mono_ir": {"timestamp": TS, "seq": 17, "label": "crab",
                                                       "confidence": 0.71,
                                                       "box": [5.4, 7.8, 15.6, 18.1]}}]}}, 50),
    ({"extra": {"name": "x", "fields": {"a": 1}}}, 40),
]  # fmt: skip


def test_golden_bytes() -> None:
    """The link encoding is a wire contract with the surface: pinned byte for byte."""
    rec, _ = RECORDS[0]
    assert LinkCodec().encode(rec).hex() == "011fe1e7d9e8900a11018e6c9c01cc01ce01"
    assert frame(DATA, b"\x01\x02").hex() == "a55a02030102238b"
    # Link protocol 2: DATA and ACK payloads open with the outbox's 4-byte session id.
    session = bytes.fromhex("c0ffee01")
    assert data_payload(session, 300, [(301, b"\x07")]).hex() == "c0ffee01ac02010107"
    assert ack_payload(session, [301, 300]).hex() == "c0ffee01ac0201"


@pytest.mark.parametrize(("record", "budget"), RECORDS)
def test_roundtrip_and_size(record: dict[str, Any], budget: int) -> None:
    codec = LinkCodec()
    data = codec.encode(record)
    assert len(data) <= budget
    assert len(data) < len(msgspec.json.encode(record))
    back = codec.decode(data)
    assert back == record


@pytest.mark.parametrize(
    "record",
    [
        {"mono_ir": {"timestamp": TS, "confidence": -0.5}},  # not representable: generic
        {"mono_ir": {"timestamp": "yesterday"}},
        {"mono_ir": {"timestamp": TS, "extra_key": 1}},
        {"stereo_vo": {"Rt": [[1, 2], [3]]}},
        {"a": 1, "b": 2},
    ],
)
def test_unfit_records_travel_generic(record: dict[str, Any]) -> None:
    data = LinkCodec().encode(record)
    assert data[0] == GENERIC
    assert LinkCodec().decode(data) == record


@pytest.mark.parametrize(
    ("data", "error"),
    [
        (b"", "expected a message body"),
        (b"\x42", "expected a record kind"),
        (b"\x02\x0f", "expected a varint"),
        (b"\x02\x04\x63", "expected a label index up to"),
        (b"\x02\x00\x00", "bytes of stereo_ir body"),
        (bytes([GENERIC]) + b"\xc1", "expected a msgpack record"),
        (bytes([GENERIC]) + msgspec.msgpack.encode([1]), "expected a msgpack map"),
        (b"\x02\x04\x00\x05ab", "expected 5 bytes"),
        (b"\x02\x01" + b"\xff" * 12, "at most 9 bytes"),
    ],
)
def test_decode_rejects(data: bytes, error: str) -> None:
    with pytest.raises(ProtocolError, match=error):
        LinkCodec().decode(data)


@pytest.mark.parametrize(
    ("kind", "payload", "error"),
    [(7, b"", "expected a frame type"), (DATA, b"x" * 256, "at most 255 bytes")],
)
def test_frame_rejects(kind: int, payload: bytes, error: str) -> None:
    with pytest.raises(ProtocolError, match=error):
        frame(kind, payload)


@pytest.mark.parametrize("value", [0, 1, 127, 128, 300, 2**40, -1, -64, -(2**40)])
def test_varints(value: int) -> None:
    out = bytearray()
    put_svarint(out, value)
    assert Reader(bytes(out)).svarint() == value
    if value >= 0:
        out = bytearray()
        put_uvarint(out, value)
        assert Reader(bytes(out)).uvarint() == value


def test_arq_payloads() -> None:
    msgs = [(105, b"abc"), (300, b""), (101, b"\x00" * 40)]
    assert parse_data(data_payload(b"\x00\x01\x02\x03", 100, msgs)) == (
        b"\x00\x01\x02\x03", 100, msgs)  # fmt: skip
    assert parse_ack(ack_payload(b"abcd", [9, 3, 1000, 3])) == (b"abcd", [3, 9, 1000])
    assert parse_ack(ack_payload(b"abcd", [])) == (b"abcd", [])


@pytest.mark.parametrize(
    ("call", "error"),
    [
        (lambda: data_payload(b"abc", 0, []), "expected a session id of 4 bytes, got 3"),
        (lambda: data_payload(b"abcde", 0, []), "expected a session id of 4 bytes, got 5"),
        (lambda: ack_payload(b"", [1]), "expected a session id of 4 bytes, got 0"),
        (lambda: parse_data(b"abc"), "expected 4 bytes at byte 0, got 3"),
        (lambda: parse_data(b"abcd"), "expected a varint at byte 4"),
        (lambda: parse_data(b"abcd\x00\x01"), "expected a varint at byte 6"),
        (lambda: parse_data(b"abcd\x00\x01\x05ab"), "expected 5 bytes at byte 7, got 2"),
        (lambda: parse_ack(b"ab"), "expected 4 bytes at byte 0, got 2"),
        (lambda: parse_ack(b"abcd\x80"), "expected a varint at byte 5"),
    ],
)
def test_arq_payloads_reject(call: Any, error: str) -> None:
    """Link protocol 2 payloads without a whole session id, or cut short, are refused."""
    with pytest.raises(ProtocolError, match=error):
        call()


def test_deframer_recovers_frames_from_garbage() -> None:
    rng = random.Random(3)
    frames = [frame(DATA, bytes(rng.randrange(256) for _ in range(rng.randrange(60))))
              for _ in range(50)]  # fmt: skip
    stream = bytearray()
    garbage = 0
    for f in frames:
        junk = bytes(rng.randrange(256) for _ in range(rng.randrange(8)))
        stream += junk + f
        garbage += len(junk)
    d = Deframer()
    got: list[tuple[int, bytes]] = []
    for i in range(0, len(stream), 7):  # arbitrary read sizes
        got += d.feed(bytes(stream[i : i + 7]))
    assert [frame(k, p) for k, p in got] == frames
    assert d.garbage_bytes == garbage


def test_deframer_drops_damaged_frame_and_keeps_the_next() -> None:
    good = frame(ACK, b"\x05")
    bad = bytearray(frame(DATA, b"hello"))
    bad[5] ^= 0x10
    d = Deframer()
    assert d.feed(bytes(bad) + good) == [(ACK, b"\x05")]
    assert d.crc_errors >= 1


def test_deframer_never_raises_on_noise() -> None:
    rng = random.Random(5)
    d = Deframer()
    for _ in range(200):
        d.feed(bytes(rng.randrange(256) for _ in range(rng.randrange(64))) + b"\xa5\x5a")
    assert d.frames <= 1 and d.garbage_bytes > 6000


def test_split_packets_cuts_frames_and_loose_bytes() -> None:
    f1, f2 = frame(DATA, b"abc"), frame(ACK, b"")
    buf = bytearray(b"xx" + f1 + f2[:3])
    assert split_packets(buf) == [b"xx", f1]
    buf += f2[3:]
    assert split_packets(buf) == [f2]
    assert not buf


@pytest.mark.parametrize("index", [1, 3, 5])  # stereo_ir, stereo_vo, tags
def test_calib_id_rides_in_four_bytes(index: int) -> None:
    """A stereo record's rig id (8 hex digits) costs 4 bytes (and a tags record's field mask
    one more) and stays compact, not generic."""
    record, budget = RECORDS[index]
    key = next(iter(record))
    stamped = {key: {**record[key], "calib": "0a1b2c3d"}}
    codec = LinkCodec()
    plain, data = codec.encode(record), codec.encode(stamped)
    assert data[0] != GENERIC and len(data) == len(plain) + (5 if key == "tags" else 4)
    assert codec.decode(data) == stamped


@pytest.mark.parametrize("calib", ["0A1B2C3D", "0a1b2c", "not-hex!", 12345678])
def test_other_calib_values_still_round_trip(calib: Any) -> None:
    record = {"stereo_ir": {"timestamp": TS, "seq": 1, "label": "crab", "confidence": 0.5,
                            "calib": calib}}
    codec = LinkCodec()
    assert codec.decode(codec.encode(record)) == record


@pytest.mark.parametrize(("reinit", "ok"), [(False, True), (True, True), (False, False)])
def test_a_vo_line_with_its_pose_fits_a_frame_and_round_trips(reinit: bool, ok: bool) -> None:
    """Issue 26 item 5: the codec had no `pose` (nor `reinit`), so every VO line went GENERIC
    at 320 bytes and the sender rejected it as too large: no VO result reached the surface.
    `pose` rides like `Rt`: rotation vector at 1e-4 rad, translation at 1e-4 m; decoded,
    rotation elements are within 2e-4 and translations within 5e-5 m of the line's."""
    from trapflow.config.modem import ModemConfig
    from trapflow.modem.frame import SESSION_BYTES

    line = builders.vo_line(reinit, ok)
    data = LinkCodec().encode(line)
    assert data[0] == 3  # the stereo_vo kind, not GENERIC
    max_body = ModemConfig().max_frame_payload - 12 - SESSION_BYTES  # the sender's limit
    assert len(data) <= 48 <= max_body, len(data)  # 46 bytes measured for the first row
    back = LinkCodec().decode(data)["stereo_vo"]
    sent = line["stereo_vo"]
    assert set(back) == set(sent)
    for key in ("timestamp", "seq", "ok", "inliers", "calib", "v"):
        assert back[key] == sent[key], key
    assert back.get("reinit", False) is reinit
    for key in ("Rt", "pose") if ok else ("pose",):
        for got, want in zip(back[key], sent[key], strict=True):
            assert max(abs(g - w) for g, w in zip(got[:3], want[:3], strict=True)) <= 2e-4, key
            assert abs(got[3] - want[3]) <= 5e-5, key


def test_a_none_line_fits_a_frame_and_an_inverted_box_still_round_trips() -> None:
    """Regression (issue 32): a mono `none` line (`box: []`) fell back to the generic form,
    104 bytes where a default frame body holds 80, so every one was refused as too large."""
    from trapflow.modem.codec import LinkCodec

    codec = LinkCodec()
    none = {"mono_ir": {"timestamp": "2026-11-29 01:00:00.123", "seq": 1234, "label": "none",
                        "confidence": 0.0, "box": [], "model": "3f9c2a1b", "v": 2}}
    wire = codec.encode(none)
    assert len(wire) <= 32 and wire[0] != 0x7F and codec.decode(wire) == none
    inverted = {"mono_ir": {**none["mono_ir"], "label": "crab", "box": [5.0, 5.0, 1.0, 9.0]}}
    assert codec.decode(codec.encode(inverted)) == inverted
