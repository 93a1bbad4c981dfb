"""The reorder window `trapflow track` streams through (trapflow.tracking.frame_window):
frames out in order with all their rows, as a sort by frame gives them, while no row is
later than the window; a later one is an error naming its line."""

from __future__ import annotations

import random
from pathlib import Path

import pytest
from click.testing import CliRunner

from trapflow.cli.main import main
from trapflow.tracking.frame_window import FrameOrderError, FrameWindow


def _through(rows: list[tuple[int, str]], frames: int) -> list[tuple[int, list[str]]]:
    w: FrameWindow[str] = FrameWindow(frames)
    out = []
    for frame, row in rows:
        out += w.add(frame, row)
    return out + w.drain()


def _sorted(rows: list[tuple[int, str]]) -> list[tuple[int, list[str]]]:
    by: dict[int, list[str]] = {}
    for frame, row in sorted(rows, key=lambda r: r[0]):  # stable: file order in a frame
        by.setdefault(frame, []).append(row)
    return sorted(by.items())


@pytest.mark.parametrize("seed", range(5))
def test_rows_a_little_late_come_out_as_a_sort_gives_them(seed: int) -> None:
    rng = random.Random(seed)
    rows = [(f, f"{f}.{i}") for f in range(1, 200) for i in range(rng.randrange(4))]
    # Each row written after the rows of up to 10 later frames, some not delayed at all.
    late = [(f + rng.choice((0, 0, rng.randrange(11))), n) for n, (f, _r) in enumerate(rows)]
    rows = [rows[n] for _k, n in sorted(late)]
    assert rows != sorted(rows, key=lambda r: r[0])
    assert _through(rows, 11) == _sorted(rows)
    with pytest.raises(FrameOrderError):
        _through(rows, 2)


def test_the_window_holds_at_most_its_frames() -> None:
    w: FrameWindow[int] = FrameWindow(3)
    gone = [g for f in range(1, 11) for g in w.add(f, f)]
    assert [f for f, _ in gone] == list(range(1, 8)) and len(w.drain()) == 3


def test_a_row_later_than_the_window_is_refused() -> None:
    w: FrameWindow[int] = FrameWindow(2)
    for f in (1, 2, 3):
        w.add(f, f)
    with pytest.raises(FrameOrderError, match="frame 1 comes after frame 1 was tracked"):
        w.add(1, 0)


def test_trapflow_track_names_the_line_of_a_frame_too_late(tmp_path: Path) -> None:
    det = tmp_path / "det.txt"
    lines = [f"{f},-1,{100 + f},50,40,30,0.9" for f in range(1, 101)]
    det.write_text("\n".join([*lines, lines[0]]) + "\n")
    res = CliRunner().invoke(main, ["track", str(det), "-o", str(tmp_path / "t.txt"),
                                    "--fps", "10"])
    assert res.exit_code == 2, res.output
    assert f"{det}:101: frame 1 comes after frame" in res.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["det.txt"]  # no half file
