"""Outbox sessions on the modem link: the outbox's identity, the surface's memory per
session, the sender's refusal of other sessions' acknowledgements (real SQLite files,
real state files, frames through a port object)."""

from __future__ import annotations

import json
import logging
import sqlite3
from pathlib import Path

import pytest

from tests.builders import BytePort, data, receive, scallop, seqs
from trapflow.config.modem import ModemConfig, OutboxConfig
from trapflow.modem.codec import LinkCodec
from trapflow.modem.frame import (
    ACK,
    DATA,
    LEGACY_ACK,
    LEGACY_DATA,
    SESSION_BYTES,
    Deframer,
    ack_payload,
    frame,
    parse_data,
    put_uvarint,
)
from trapflow.modem.outbox import Outbox, OutboxError, OutboxQueue
from trapflow.modem.sender import ModemSender
from trapflow.modem.surface_state import MAX_SESSIONS, load_state

A, B, C = bytes.fromhex("aaaa0001"), bytes.fromhex("bbbb0002"), bytes.fromhex("cccc0003")


def acks(port: BytePort) -> list[tuple[str, list[int]]]:
    """(session hex, ids) of every ACK the receiver wrote, in order."""
    out = []
    for kind, payload in Deframer().feed(bytes(port.sent)):
        assert kind == ACK
        session, rest = payload[:SESSION_BYTES], payload[SESSION_BYTES:]
        ids, prev, value, shift = [], 0, 0, 0
        for byte in rest:  # LEB128 deltas, decoded here without the library's reader
            value |= (byte & 0x7F) << shift
            shift += 7
            if byte < 0x80:
                prev += value
                ids.append(prev)
                value = shift = 0
        out.append((session.hex(), ids))
    return out


# Each case: frames (session, floor, ids) fed to one surface in order, then the ids written
# (by the record's seq field, which here equals the message id) and the ACKs sent.
SURFACE_CASES = [
    pytest.param(
        [(A, 1, [1, 2, 3]), (A, 4, [4, 5]), (B, 1, [1, 2, 3])],
        [1, 2, 3, 4, 5, 1, 2, 3],
        [("aaaa0001", [1, 2, 3]), ("aaaa0001", [4, 5]), ("bbbb0002", [1, 2, 3])],
        id="fresh-outbox-below-the-old-floor-is-written",
    ),
    pytest.param(
        [(A, 1, [1, 2]), (B, 1, [1]), (A, 1, [2, 3]), (B, 1, [1, 2])],
        [1, 2, 1, 3, 2],
        [("aaaa0001", [1, 2]), ("bbbb0002", [1]), ("aaaa0001", [2, 3]), ("bbbb0002", [1, 2])],
        id="two-outboxes-interleaved-each-deduplicated-on-its-own",
    ),
    pytest.param(
        [(A, 50, [50, 51]), (B, 900, [900]), (A, 51, [51, 52])],
        [50, 51, 900, 52],
        [("aaaa0001", [50, 51]), ("bbbb0002", [900]), ("aaaa0001", [51, 52])],
        id="another-session-does-not-move-this-ones-floor",
    ),
    pytest.param(
        [(A, 1, [1, 2]), (A, 1, [1]), (A, 3, [3]), (A, 1, [2])],
        [1, 2, 3],
        [("aaaa0001", [1, 2]), ("aaaa0001", [1]), ("aaaa0001", [3]), ("aaaa0001", [2])],
        id="retransmission-in-one-session-is-acked-not-written",
    ),
    pytest.param(
        [(C, 7, [7, 9, 8])],
        [7, 9, 8],
        [("cccc0003", [7, 8, 9])],
        id="first-frame-of-a-session-above-1-is-all-new",
    ),
]


def _feed(out: Path, state: Path | None, frames: list[tuple[bytes, int, list[int]]]) -> BytePort:
    _, port = receive(out, state, *(data(f, ids, s) for s, f, ids in frames))
    return port


@pytest.mark.parametrize(("frames", "written", "acked"), SURFACE_CASES)
@pytest.mark.parametrize("with_state", [False, True])
def test_surface_memory_is_per_session(
    tmp_path: Path,
    frames: list[tuple[bytes, int, list[int]]],
    written: list[int],
    acked: list[tuple[str, list[int]]],
    with_state: bool,
) -> None:
    """Regression for issue 16 item 1: with one memory for every outbox, a fresh outbox's
    ids (from 1 again) were taken for retransmissions, acknowledged and never written."""
    out = tmp_path / "surface.jsonl"
    state = tmp_path / "surface.jsonl.state" if with_state else None
    port = _feed(out, state, frames)
    assert seqs(out) == written
    assert acks(port) == acked
    # An ACK is sent only for ids the output holds: nothing acknowledged goes unwritten.
    for _, ids in acks(port):
        assert set(ids) <= set(seqs(out))


def test_sessions_survive_a_surface_restart(tmp_path: Path) -> None:
    out, state = tmp_path / "surface.jsonl", tmp_path / "surface.jsonl.state"
    _feed(out, state, [(A, 1, [1, 2]), (B, 1, [1])])
    assert [(s.id, s.floor, s.seen) for s in load_state(state).sessions] == [
        ("aaaa0001", 1, [1, 2]), ("bbbb0002", 1, [1])]  # fmt: skip
    # Restarted surface: both outboxes retransmit (ACKs lost) and go on.
    port = _feed(out, state, [(A, 1, [2, 3]), (B, 1, [1, 2])])
    assert seqs(out) == [1, 2, 1, 3, 2]
    assert acks(port) == [("aaaa0001", [2, 3]), ("bbbb0002", [1, 2])]
    assert [s.id for s in load_state(state).sessions] == ["aaaa0001", "bbbb0002"]


def test_oldest_session_is_forgotten_beyond_the_limit(tmp_path: Path) -> None:
    """A forgotten session's retransmission is written again: a duplicate, never a loss."""
    out, state = tmp_path / "surface.jsonl", tmp_path / "surface.jsonl.state"
    ids = [i.to_bytes(4, "big") for i in range(1, MAX_SESSIONS + 2)]
    frames = [(sid, 1, [1]) for sid in ids]
    rx, _ = receive(out, state, *(data(f, i, s) for s, f, i in frames))
    assert rx.new_sessions == MAX_SESSIONS + 1 and len(rx.sessions) == MAX_SESSIONS
    kept = [s.id for s in load_state(state).sessions]
    assert kept == [sid.hex() for sid in ids[1:]]
    again, _ = receive(out, state, data(1, [1], ids[0]), data(1, [1], ids[-1]))
    assert (again.written, again.duplicates) == (1, 1)


def test_protocol_1_data_is_refused_by_name(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A box still on link protocol 1 is never acknowledged (it keeps its records)."""
    old = bytearray()
    put_uvarint(old, 0)
    put_uvarint(old, 0)
    body = LinkCodec().encode(scallop(0))
    put_uvarint(old, len(body))
    with caplog.at_level(logging.ERROR, logger="trapflow.modem.surface"):
        rx, port = receive(
            tmp_path / "o.jsonl", None, frame(LEGACY_DATA, bytes(old) + body), data(1, [1], A)
        )
    assert (rx.legacy_frames, rx.written, rx.bad_frames) == (1, 1, 0)
    assert acks(port) == [("aaaa0001", [1])]
    assert "link protocol 1" in caplog.text and "update trapflow on the box" in caplog.text


# --- format 1 state files ------------------------------------------------------------


@pytest.mark.parametrize(
    ("content", "remembered"),
    [
        (b'{"version": 1, "floor": 3, "seen": [3, 4]}', 2),
        (b'{"version": 1}', 0),
        (b'{"version": 1, "floor": 0, "seen": [0], "output": null}', 1),
    ],
)
def test_format_1_state_loads_without_ids_and_is_rewritten(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, content: bytes, remembered: int
) -> None:
    out, state = tmp_path / "surface.jsonl", tmp_path / "surface.jsonl.state"
    state.write_bytes(content)
    with caplog.at_level(logging.WARNING, logger="trapflow.modem.surface_state"):
        rx, port = receive(out, state, data(3, [3], A))
    assert "is format 1" in caplog.text and f"its {remembered} remembered ids" in caplog.text
    assert (rx.written, acks(port)) == (1, [("aaaa0001", [3])])
    assert json.loads(state.read_bytes())["version"] == 2


def test_format_1_output_mark_still_cuts_unacknowledged_lines(tmp_path: Path) -> None:
    out, state = tmp_path / "surface.jsonl", tmp_path / "surface.jsonl.state"
    out.write_text(json.dumps(scallop(0)) + "\n")
    st = out.stat()
    mark = {"dev": st.st_dev, "ino": st.st_ino, "size": st.st_size}
    state.write_text(json.dumps({"version": 1, "floor": 0, "seen": [0], "output": mark}))
    with open(out, "a") as f:  # written after the last save: never acknowledged
        f.write(json.dumps(scallop(1)) + "\n")
    rx, _ = receive(out, state, data(1, [1], A))
    assert rx.cut_bytes > 0 and seqs(out) == [0, 1]


# --- the outbox's identity ---------------------------------------------------------------


def test_outbox_session_is_kept_in_the_file(tmp_path: Path) -> None:
    path = tmp_path / "outbox.sqlite"
    queue = OutboxQueue(path, OutboxConfig())  # the sender may open it first
    box = Outbox(path, OutboxConfig())
    assert len(box.session) == SESSION_BYTES and box.session == queue.session
    box.append(scallop(1))
    box.close()
    queue.close()
    assert Outbox(path, OutboxConfig()).session == box.session  # a restart keeps it
    (row,) = sqlite3.connect(path).execute("SELECT value FROM meta WHERE key='session'")
    assert row[0] == box.session
    fresh = [Outbox(tmp_path / f"fresh{i}.sqlite", OutboxConfig()) for i in range(8)]
    sessions = {b.session for b in fresh} | {box.session}
    assert len(sessions) == 9, "a fresh outbox drew the session of another"
    for b in fresh:
        b.close()


def test_outbox_from_before_sessions_gets_one_and_keeps_its_records(tmp_path: Path) -> None:
    path = tmp_path / "outbox.sqlite"
    Outbox(path, OutboxConfig()).append(scallop(1))
    db = sqlite3.connect(path)
    db.execute("DROP TABLE meta")  # as written by trapflow before link protocol 2
    db.commit()
    db.close()
    box = Outbox(path, OutboxConfig())
    assert len(box.session) == SESSION_BYTES
    assert [s.record() for s in box.read()] == [scallop(1)]
    box.close()


@pytest.mark.parametrize("value", [b"", b"abc", b"abcde", b"x" * 16])
def test_damaged_outbox_session_is_refused(tmp_path: Path, value: bytes) -> None:
    path = tmp_path / "outbox.sqlite"
    Outbox(path, OutboxConfig()).close()
    db = sqlite3.connect(path)
    db.execute("UPDATE meta SET value=? WHERE key='session'", (value,))
    db.commit()
    db.close()
    with pytest.raises(OutboxError, match=rf"expected a 4-byte session id .* got {len(value)} "
                       r"bytes; .* move it aside"):  # fmt: skip
        OutboxQueue(path, OutboxConfig())


# --- the sender ----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("reply", "settled", "counter"),
    [
        (lambda own: frame(ACK, ack_payload(own, [1, 2])), {1, 2}, "acked"),
        (lambda own: frame(ACK, ack_payload(A if own != A else B, [1, 2])), set(), "foreign_acks"),
        (lambda own: frame(LEGACY_ACK, b"\x01\x01"), set(), "unexpected_frames"),
        (lambda own: frame(ACK, own[:3]), set(), "bad_acks"),
    ],
)
def test_sender_settles_only_acks_of_its_own_session(
    tmp_path: Path, reply: object, settled: set[int], counter: str
) -> None:
    """Regression for issue 16 item 1: an ACK still on its way from before the box was
    restarted with a fresh outbox named the old outbox's seqs, and would settle the new
    outbox's records of the same numbers."""
    path = tmp_path / "outbox.sqlite"
    box = Outbox(path, OutboxConfig())
    box.append_many([scallop(1), scallop(2)])
    port = BytePort()
    sender = ModemSender(path, port, ModemConfig(bit_rate=1e6, aggregate=[], ttl_s={}))
    sender.step()
    ((kind, payload),) = Deframer().feed(bytes(port.sent))
    session, _, messages = parse_data(payload)
    assert (kind, session, [i for i, _ in messages]) == (DATA, box.session, [1, 2])
    port.incoming += reply(box.session)  # type: ignore[operator]
    sender.step()
    assert sender.stats().get(counter, 0) >= 1
    assert sender.queue.states() == ({"acked": len(settled)} if settled else {})
    assert sender.queue.counts()[2] == 2 - len(settled)
    sender.close()
    box.close()

