"""`trapflow track` on MOTChallenge files: ids out, clear errors with file and line."""

from __future__ import annotations

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
