"""MOTChallenge text files: parsing with errors that name file and line, the frame rate from
seqinfo.ini, a write-read round trip, and track_file end to end on a small sequence."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from trapflow.errors import TrapflowError
from trapflow.tracking.motformat import (
    MotFormatError,
    MotRow,
    read_fps,
    read_mot,
    track_file,
    write_mot,
)

GOOD_LINES = [
    # (line, row)
    # A MOT17 detection: id -1, world coordinates -1.
    ("1,-1,10.5,20,30,40,0.9,-1,-1,-1",
     MotRow(frame=1, id=-1, x=10.5, y=20, w=30, h=40, conf=0.9, cls=-1)),
    # Ground truth: considered flag as conf, class 1, visibility.
    ("7,3,1,2,3,4,1,1,0.5", MotRow(frame=7, id=3, x=1, y=2, w=3, h=4, conf=1.0, cls=1)),
    # Only the six required columns: conf 1.
    ("2, 5, 0, 0, 8, 9", MotRow(frame=2, id=5, x=0, y=0, w=8, h=9, conf=1.0, cls=-1)),
    # Frame written as a float (some tools do).
    ("3.0,-1,1,1,2,2,0.4", MotRow(frame=3, id=-1, x=1, y=1, w=2, h=2, conf=0.4, cls=-1)),
]


@pytest.mark.parametrize(("line", "row"), GOOD_LINES)
def test_reads_good_lines(tmp_path: Path, line: str, row: MotRow) -> None:
    f = tmp_path / "det.txt"
    f.write_text(line + "\n\n")  # a blank line is skipped
    assert read_mot(f) == [row]


BAD_LINES = [
    # (line, error expected)
    # Too few columns.
    ("1,-1,10,20,30", "(at least 6 comma-separated columns), got '1,-1,10,20,30'"),
    # Not a number.
    ("1,-1,ten,20,30,40,0.9", "x: expected a number, got 'ten'"),
    # Frames count from 1.
    ("0,-1,10,20,30,40,0.9", "frame: expected 1 or more, got '0'"),
    # A fractional frame.
    ("1.5,-1,10,20,30,40", "frame: expected a whole number, got '1.5'"),
    # An empty box.
    ("1,-1,10,20,0,40,0.9", "expected a box of positive width and height, got w=0 h=40"),
    # NaN is a float to Python, not a number here.
    ("1,-1,10,20,30,40,nan", "conf: expected a finite number, got 'nan'"),
    # Tab-separated: one column.
    ("1\t-1\t10\t20\t30\t40", "at least 6 comma-separated columns"),
    # Out of range (issue 36 item 8: an OverflowError traceback, or numpy overflow warnings
    # and exit 0): one line naming the field.
    ("1e300,-1,10,20,30,40,0.9", "frame: expected a number from -1e+09 to 1e+09, got '1e300'"),
    ("1,1e300,10,20,30,40,0.9", "id: expected a number from -1e+09 to 1e+09"),
    ("1,-1,1e308,20,30,40,0.9", "x: expected a number from -1e+07 to 1e+07, got '1e308'"),
    ("1,-1,10,20,1e308,40,0.9", "w: expected a number from -1e+07 to 1e+07, got '1e308'"),
    ("1,-1,10,-1e308,30,40,0.9", "y: expected a number from -1e+07 to 1e+07"),
    ("1,-1,10,20,30,40,1e300", "conf: expected a number from -1e+06 to 1e+06"),
    ("1,-1,10,20,30,40,0.9,1e300", "class: expected a number from -1e+09 to 1e+09"),
]


@pytest.mark.parametrize(("line", "error"), BAD_LINES)
def test_bad_lines_name_file_and_line(tmp_path: Path, line: str, error: str) -> None:
    f = tmp_path / "det.txt"
    f.write_text("1,-1,1,1,5,5,0.9\n" + line + "\n")
    with pytest.raises(MotFormatError) as exc:
        read_mot(f)
    assert str(exc.value).startswith(f"{f}:2: ")
    assert error in str(exc.value)
    assert isinstance(exc.value, TrapflowError)


def test_missing_file_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(MotFormatError, match="cannot read"):
        read_mot(tmp_path / "nope.txt")


SEQINFO = [
    # (where seqinfo.ini is, its text, fps or error)
    # MOT layout: SEQ/det/det.txt with SEQ/seqinfo.ini.
    ("up", "[Sequence]\nname=a\nframeRate=30\n", 30.0),
    # Beside the file.
    ("beside", "[Sequence]\nframeRate=12.5\n", 12.5),
    # No frameRate key.
    ("beside", "[Sequence]\nname=a\n", "expected [Sequence] frameRate=N"),
    # Zero.
    ("beside", "[Sequence]\nframeRate=0\n", "frameRate: expected more than 0"),
    # No file at all.
    (None, "", "no seqinfo.ini beside it or one folder up"),
]


@pytest.mark.parametrize(("where", "text", "expected"), SEQINFO)
def test_frame_rate_from_seqinfo(tmp_path: Path, where: str | None, text: str,
                                 expected: float | str) -> None:
    det = tmp_path / "seq" / "det" / "det.txt"
    det.parent.mkdir(parents=True)
    det.write_text("")
    if where is not None:
        folder = det.parent if where == "beside" else det.parent.parent
        (folder / "seqinfo.ini").write_text(text)
    if isinstance(expected, float):
        assert read_fps(det) == expected
    else:
        with pytest.raises(MotFormatError, match=re.escape(expected)):
            read_fps(det)


def test_write_then_read_round_trip(tmp_path: Path) -> None:
    rows = [MotRow(frame=2, id=1, x=1.25, y=2.5, w=30, h=40, conf=0.875),
            MotRow(frame=1, id=2, x=100, y=200, w=10.5, h=20.75, conf=0.5)]
    f = tmp_path / "tracks.txt"
    write_mot(f, rows)
    assert f.read_text().splitlines()[0] == "1,2,100.00,200.00,10.50,20.75,0.5,-1,-1,-1"
    assert read_mot(f) == sorted(rows, key=lambda r: r.frame)


def test_track_file_gives_each_walker_one_id(tmp_path: Path) -> None:
    """Two boxes walking apart, detected on every third frame at 15 fps (seqinfo.ini): two
    ids, each kept; the first detection of each is tentative and not written."""
    seq = tmp_path / "seq"
    (seq / "det").mkdir(parents=True)
    (seq / "seqinfo.ini").write_text("[Sequence]\nframeRate=15\n")
    lines = []
    for frame in range(1, 61, 3):
        lines.append(f"{frame},-1,{100 + frame},100,40,40,0.9,-1,-1,-1")
        lines.append(f"{frame},-1,{400 - frame},300,40,40,0.8,-1,-1,-1")
    (seq / "det" / "det.txt").write_text("\n".join(lines) + "\n")
    out = tmp_path / "tracks.txt"
    summary = track_file(seq / "det" / "det.txt", out)
    assert (summary.detections, summary.tracks, summary.tracked, summary.fps) == (40, 2, 38, 15)
    rows = read_mot(out)
    assert {r.id for r in rows if r.y == 100} == {1}
    assert {r.id for r in rows if r.y == 300} == {2}


def test_track_file_refuses_a_bad_fps(tmp_path: Path) -> None:
    f = tmp_path / "det.txt"
    f.write_text("")
    with pytest.raises(MotFormatError, match="fps: expected more than 0"):
        track_file(f, tmp_path / "out.txt", fps=0.0)
