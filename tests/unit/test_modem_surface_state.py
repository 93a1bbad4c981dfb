"""The surface's de-duplication memory survives a restart: real output and state files,
frames fed through a port object."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import msgspec
import pytest

from tests.builders import SESSION, data, receive, scallop, seqs
from trapflow.modem.surface import SurfaceReceiver
from trapflow.modem.surface_state import SessionState, SurfaceState, load_state


def memory(rx: SurfaceReceiver, session: bytes = SESSION) -> tuple[int, set[int]]:
    """(floor, seen) the receiver keeps for a session."""
    return rx.sessions[session].floor, rx.sessions[session].seen


def saved(state: Path, session: bytes = SESSION) -> tuple[int, list[int]]:
    """(floor, seen) the state file keeps for a session."""
    (one,) = [s for s in load_state(state).sessions if s.id == session.hex()]
    return one.floor, one.seen


def test_retransmission_after_restart_is_not_written_again(tmp_path: Path) -> None:
    out, state = tmp_path / "surface.jsonl", tmp_path / "surface.jsonl.state"
    first, port = receive(out, state, data(0, [0, 1]), data(0, [2]))
    assert first.written == 3 and port.acked() == [0, 1, 2]
    assert first.state_saves == 2
    # The ACK for [2] was lost; the surface restarts; the sender retransmits 1 and 2 and sends 3.
    second, port = receive(out, state, data(0, [1, 2]), data(0, [2, 3]))
    assert (second.written, second.duplicates) == (1, 3)
    assert port.acked() == [1, 2, 2, 3]  # duplicates are acknowledged again
    assert second.state_saves == 1  # the frame with no new id rewrote nothing
    assert seqs(out) == [0, 1, 2, 3]


def test_without_state_file_a_restart_forgets(tmp_path: Path) -> None:
    """Today's in-memory behaviour (standard output): the duplicate is written again."""
    out = tmp_path / "surface.jsonl"
    receive(out, None, data(0, [0, 1]))
    second, _ = receive(out, None, data(0, [1]))
    assert (second.written, second.duplicates) == (1, 0)
    assert seqs(out) == [0, 1, 1]
    assert not list(tmp_path.glob("*.state"))


@pytest.mark.parametrize(
    ("content", "error"),
    [
        (b"", "corrupt"),
        (b'{"version": 2, "sessions": [{"id": "5e551011", "fl', "corrupt"),
        (b"\xff\xfe garbage", "corrupt"),
        (b"[2]", "Expected `object`, got `array`"),
        (b'{"version": "2"}', "Expected `int`, got `str` - at `$.version`"),
        (b'{"version": 2, "sessions": [{"id": "5e551011", "floor": -1}]}',
         "Expected `int` >= 0 - at `$.sessions[0].floor`"),
        (b'{"version": 2, "sessions": [{"id": "5E55", "floor": 0}]}',
         "Expected `str` matching regex"),
        (b'{"version": 3, "sessions": []}', "Expected `int` <= 2 - at `$.version`"),
        (b'{"version": 0, "sessions": []}', "Expected `int` >= 2 - at `$.version`"),
        (b'{"version": 2, "sessions": [{"id": "5e551011", "seen": ["a"]}]}',
         "Expected `int`, got `str`"),
        (b'{"version": 2, "sessions": [], "x": 1}', "unknown field `x`"),
        (b'{"version": 1, "floor": -1, "seen": []}', "Expected `int` >= 0 - at `$.floor`"),
        (b'{"version": 1, "floor": 0, "seen": [], "x": 1}', "unknown field `x`"),
        (None, "unreadable"),  # a directory where the file should be
    ],
)
def test_corrupt_state_warns_and_starts_empty(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, content: bytes | None, error: str
) -> None:
    out, state = tmp_path / "surface.jsonl", tmp_path / "surface.jsonl.state"
    if content is None:
        state.mkdir()
    else:
        state.write_bytes(content)
    with caplog.at_level(logging.WARNING, logger="trapflow.modem.surface_state"):
        rx, port = receive(out, state, data(0, [0]))
    assert str(state) in caplog.text and error in caplog.text
    assert (memory(rx), rx.written) == ((0, {0}), 1)
    if content is not None:  # the bad file is replaced by a good one at the first save
        assert load_state(state) == SurfaceState(
            sessions=[SessionState(id=SESSION.hex(), floor=0, seen=[0])],
            output=load_state(state).output,
        )
        assert port.acked() == [0]
    else:  # cannot save over a directory: never acknowledged, so the sender keeps it
        assert port.acked() == [] and rx.state_saves == 0


def test_floor_pruning_after_reload(tmp_path: Path) -> None:
    out, state = tmp_path / "surface.jsonl", tmp_path / "surface.jsonl.state"
    receive(out, state, data(0, [0, 1, 2, 3, 4]))
    assert saved(state) == (0, [0, 1, 2, 3, 4])
    # Restarted: the sender settled 0..2, retransmits 3 (ack lost) and sends 5.
    second, _ = receive(out, state, data(3, [3, 5]))
    assert memory(second) == (3, {3, 4, 5})
    assert saved(state) == (3, [3, 4, 5])
    # Restarted again: a stale frame's id below the floor is settled, never written.
    third, _ = receive(out, state, data(0, [2]), data(3, [4, 6]), data(6, [6, 7]))
    assert (third.written, third.duplicates) == (2, 3)
    assert saved(state) == (6, [6, 7])
    assert seqs(out) == [0, 1, 2, 3, 4, 5, 6, 7]


def test_lines_written_after_the_last_save_are_cut_on_load(tmp_path: Path) -> None:
    """A kill between writing lines and saving the state: those lines were never acked,
    so they are cut and written again when the sender retransmits, exactly once."""
    out, state = tmp_path / "surface.jsonl", tmp_path / "surface.jsonl.state"
    receive(out, state, data(0, [0, 1]))
    saved = state.read_bytes()
    receive(out, state, data(0, [2]))
    state.write_bytes(saved)  # as if killed before the state for id 2 was saved
    again, port = receive(out, state, data(0, [2, 3]))
    assert again.cut_bytes > 0 and again.written == 2 and port.acked() == [2, 3]
    assert seqs(out) == [0, 1, 2, 3]
    assert msgspec.json.decode(state.read_bytes())["output"]["size"] == out.stat().st_size


def test_state_of_another_output_keeps_the_output_whole(tmp_path: Path) -> None:
    state = tmp_path / "shared.state"
    receive(tmp_path / "old.jsonl", state, data(0, [0, 1]))
    new = tmp_path / "new.jsonl"
    new.write_text("".join(json.dumps(scallop(90 + k)) + "\n" for k in range(5)))
    assert new.stat().st_size > (tmp_path / "old.jsonl").stat().st_size  # would be cut
    rx, _ = receive(new, state, data(0, [1, 2]))
    assert rx.cut_bytes == 0 and seqs(new) == [90, 91, 92, 93, 94, 2]
