"""`trapflow track` on MOTChallenge files: ids out, clear errors with file and line."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import pytest
from click.testing import CliRunner

from trapflow.cli.main import main


def test_track_writes_ids(tmp_path: Path) -> None:
    det = tmp_path / "det.txt"
    det.write_text("".join(f"{f},-1,{100 + 2 * f},50,40,30,0.9\n" for f in range(1, 11)))
    out = tmp_path / "tracks.txt"
    res = CliRunner().invoke(main, ["track", str(det), "-o", str(out), "--fps", "10"])
    assert res.exit_code == 0, res.output
    ids = {line.split(",")[1] for line in out.read_text().splitlines()}
    assert ids == {"1"} and "1 tracks" in res.output


def test_a_bad_line_is_named_and_exits_2(tmp_path: Path) -> None:
    det = tmp_path / "det.txt"
    det.write_text("1,-1,100,50,40,30,0.9\n2,-1,abc,50,40,30,0.9\n")
    res = CliRunner().invoke(main, ["track", str(det), "-o", str(tmp_path / "o.txt"),
                                    "--fps", "10"])
    assert res.exit_code == 2 and f"{det}:2" in res.output


def test_no_frame_rate_anywhere_is_a_clear_error(tmp_path: Path) -> None:
    det = tmp_path / "det.txt"
    det.write_text("1,-1,100,50,40,30,0.9\n")
    res = CliRunner().invoke(main, ["track", str(det), "-o", str(tmp_path / "o.txt")])
    assert res.exit_code == 2 and "seqinfo.ini" in res.output


@pytest.mark.parametrize(("rows", "field"), [
    ("1,-1,1,2,3,4,0.9\n1e300,-1,1,2,3,4,0.9\n", "frame"),
    ("1,-1,1e308,2,1e308,4,0.9\n2,-1,1e308,2,1e308,4,0.9\n", "x"),
])
def test_a_field_out_of_range_is_one_line_and_exits_2(tmp_path: Path, rows: str,
                                                      field: str) -> None:
    """Regression for issue 36 item 8: a frame number of 1e300 printed an OverflowError
    traceback; 1e308 coordinates gave numpy overflow warnings and exit 0."""
    det = tmp_path / "det.txt"
    det.write_text(rows)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a numpy overflow warning fails the test
        res = CliRunner().invoke(main, ["track", str(det), "-o", str(tmp_path / "o.txt"),
                                        "--fps", "10"])
    assert res.exit_code == 2, res.output
    assert f"{det}:{rows.count(chr(10)) if field == 'frame' else 1}: {field}: expected" \
        in res.output
    assert "Traceback" not in res.output and len(res.output.strip().splitlines()) <= 3


def test_track_writes_counts_per_class(tmp_path: Path) -> None:
    """`trapflow track` writes the counts a live run writes (issue 35): per interval and
    class (the MOT class column) visits, MaxN (confirmed tracks at one frame) and dwell."""
    det = tmp_path / "det.txt"
    # Frames 1-20 at 10 fps: two fish (class 1) side by side, one crab (class 2) from
    # frame 11; a 1 s interval: two intervals.
    rows = []
    for f in range(1, 21):
        rows += [f"{f},-1,{100 + f},50,40,30,0.9,1", f"{f},-1,{100 + f},200,40,30,0.9,1"]
        if f > 10:
            rows.append(f"{f},-1,400,{300 + f},40,30,0.9,2")
    det.write_text("\n".join(rows) + "\n")
    out = tmp_path / "tracks.txt"
    res = CliRunner().invoke(main, ["track", str(det), "-o", str(out), "--fps", "10",
                                    "--interval", "1"])
    assert res.exit_code == 0, res.output
    lines = [json.loads(x)["counts"]
             for x in (tmp_path / "tracks.counts.jsonl").read_text().splitlines()]
    assert [(c["start_s"], c["pairs"]) for c in lines] == [(0.0, 10), (1.0, 10)]
    first = {c["label"]: c for c in lines[0]["labels"]}
    second = {c["label"]: c for c in lines[1]["labels"]}
    assert first["1"]["visits"] == 2 and first["1"]["max_n"] == 2 and "2" not in first
    assert second["1"]["visits"] == 0 and second["1"]["max_n"] == 2
    assert second["2"]["visits"] == 1 and second["2"]["max_n"] == 1
    # dwell: from each track's confirming box (frame 2; frame 12 for the crab) to its last
    assert first["1"]["dwell_s"] + second["1"]["dwell_s"] == pytest.approx(2 * 1.8)
    assert second["2"]["dwell_s"] == pytest.approx(0.8)
    assert "2 counting intervals" in res.output
