"""`trapflow track` on MOTChallenge files: ids out, clear errors with file and line."""

from __future__ import annotations

from pathlib import Path

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
