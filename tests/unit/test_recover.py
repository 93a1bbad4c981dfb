"""recover(): a recording cut anywhere keeps every message of its complete chunks, byte for
byte, as a valid MCAP; checked against the uncut file's own index and read back by rosbags."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from trapflow.recording.recorder import Recorder, RecorderError, recover, recovered_name
from trapflow.wire.messages import StereoPair

W, H = 64, 48
PAIRS, PER_CHUNK = 40, 10  # three messages (left, right, header) per pair


def write(path: Path) -> None:
    with Recorder(path) as rec:
        for i in range(PAIRS):
            h = StereoPair(seq=i, t_wall_ns=10**18 + i * 10**8, t_mono_ns=i, t_left_ns=i,
                           t_right_ns=i, skew_ns=0, encoding="jpeg", width=W, height=H)
            img = np.random.default_rng(i).integers(0, 255, (H, W, 3), np.uint8)
            jpg = cv2.imencode(".jpg", img)[1].tobytes()
            rec.add_pair(h, jpg, jpg)
            if i % PER_CHUNK == PER_CHUNK - 1:
                rec._writer._writer.flush()  # what the one-second flush does, made exact


def read_all(path: Path) -> list[tuple[str, int, bytes]]:
    with AnyReader([path]) as reader:
        return [(c.topic, t, bytes(raw)) for c, t, raw in reader.messages()]


@pytest.fixture(scope="module")
def whole(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "whole.mcap"
    write(path)
    return path


def chunk_ends(path: Path) -> list[int]:
    """Where each chunk ends, from the complete file's summary (the seeking reader's index)."""
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return sorted(c.chunk_start_offset + c.chunk_length for c in summary.chunk_indexes)


@pytest.mark.parametrize("fraction", [0.05, 0.3, 0.5, 0.74, 0.99, 1.0])
def test_a_cut_recording_keeps_every_complete_chunk(whole: Path, tmp_path: Path,
                                                    fraction: float) -> None:
    data = whole.read_bytes()
    ends = chunk_ends(whole)
    assert len(ends) == PAIRS // PER_CHUNK
    cut = int(len(data) * fraction)
    part = tmp_path / "cut.mcap.part"
    part.write_bytes(data[:cut])
    out = recovered_name(part)
    assert out == tmp_path / "cut.mcap"
    n = recover(part, out)
    complete = sum(1 for e in ends if e <= cut)
    assert n == complete * PER_CHUNK * 3
    assert part.read_bytes() == data[:cut]  # the input is never written
    got = read_all(out)
    assert got == read_all(whole)[:n]  # the same messages, in order, byte for byte


@pytest.mark.parametrize(
    ("content", "error"),
    [
        (b"", "not an MCAP recording"),
        (b"\x89MCAP0\r\n", "not an MCAP recording"),
        (b"PK\x03\x04 a zip file, not a recording", "not an MCAP recording"),
    ],
)
def test_what_is_not_a_recording_is_refused(tmp_path: Path, content: bytes, error: str) -> None:
    part = tmp_path / "x.mcap.part"
    part.write_bytes(content)
    with pytest.raises(RecorderError, match=error):
        recover(part, tmp_path / "x.mcap")
    assert not (tmp_path / "x.mcap").exists() and part.read_bytes() == content


def test_recover_refuses_to_write_over_its_input(tmp_path: Path) -> None:
    part = tmp_path / "x.mcap"
    part.write_bytes(b"\x89MCAP0\r\n")
    with pytest.raises(RecorderError, match="is the input"):
        recover(part, part)
