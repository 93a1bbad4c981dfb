"""Exports and reports of a run still going or damaged: a run still going is refused (exit
2, nothing written); a damaged one (a last line cut mid-way, results.jsonl cut short, tracks
missing) is written as far as it is whole, with one line per cut saying what it leaves out,
and exit 1. Before, a run still going gave "0 media, 0 observations" and exit 0, and a cut
tracks.jsonl silently gave 4 observations of 5."""

from __future__ import annotations

import csv
import os
from pathlib import Path

from click.testing import CliRunner, Result

from tests.unit.made_run import make_run, results, stamp, t_of, tracks, write_lines
from trapflow.cli.main import main
from trapflow.export.camtrap_obs import iso, utc


def _export(run: Path, out: Path) -> Result:
    return CliRunner().invoke(main, ["export", "camtrapdp", str(run), str(out),
                                     "--latitude", "50", "--longitude", "-4"])


def _report(run: Path, out: Path) -> Result:
    return CliRunner().invoke(main, ["report", str(run), "-o", str(out)])


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def _warnings(res: Result) -> list[str]:
    return [line.removeprefix("trapflow: warning: ") for line in res.stderr.splitlines()
            if line.startswith("trapflow: warning: ")]


def test_a_run_still_going_is_refused(tmp_path: Path) -> None:
    run = make_run(tmp_path / "run")
    (run / "supervisor.lock").write_text(str(os.getpid()))  # a live process holds it
    res = _export(run, tmp_path / "pkg")
    assert res.exit_code == 2 and "a run still going" in res.stderr, res.stderr
    assert not (tmp_path / "pkg").exists()
    res = _report(run, tmp_path / "page.html")
    assert res.exit_code == 2 and "a run still going" in res.stderr, res.stderr
    assert not (tmp_path / "page.html").exists()
    # After a crash the lock stays, naming no process: the run is over, and exported.
    (run / "supervisor.lock").write_text("999999999")
    assert _export(run, tmp_path / "pkg").exit_code == 0


def test_a_whole_run_exports_without_a_word(tmp_path: Path) -> None:
    run = make_run(tmp_path / "run")
    res = _export(run, tmp_path / "pkg")
    assert res.exit_code == 0 and res.stderr == "", res.stderr
    assert len([o for o in _rows(tmp_path / "pkg" / "observations.csv")
                if o["observationLevel"] == "event"]) == 2
    res = _report(run, tmp_path / "page.html")
    assert res.exit_code == 0 and res.stderr == "", res.stderr


def test_results_cut_in_half(tmp_path: Path) -> None:
    run = make_run(tmp_path / "run")
    write_lines(run / "results.jsonl", results()[:8])  # pairs 1-4 of mono and VO
    res = _export(run, tmp_path / "pkg")
    assert res.exit_code == 1, res.output
    assert _warnings(res) == [
        "results.jsonl holds 4 of the 8 results ledger.json counts for pool mono: the pairs "
        "of the other 4 are left out",
        "results.jsonl holds 4 of the 8 results ledger.json counts for pool vo: the pairs "
        "of the other 4 are left out",
        f"results.jsonl ends at {stamp(4)}, before track 2 end: the boxes, best frames and "
        "blanks after it are left out"]
    # What is whole is written: both tracks, and a deployment that spans them.
    assert len([o for o in _rows(tmp_path / "pkg" / "observations.csv")
                if o["observationLevel"] == "event"]) == 2
    (dep,) = _rows(tmp_path / "pkg" / "deployments.csv")
    assert dep["deploymentEnd"] == iso(utc(t_of(8)))
    res = _report(run, tmp_path / "page.html")
    assert res.exit_code == 1 and len(_warnings(res)) == 3
    assert (tmp_path / "page.html").is_file()


def test_tracks_cut_mid_line(tmp_path: Path) -> None:
    run = make_run(tmp_path / "run")
    text = (run / "tracks.jsonl").read_text()
    (run / "tracks.jsonl").write_text(text[: len(text) - 40])
    res = _export(run, tmp_path / "pkg")
    assert res.exit_code == 1, res.output
    assert _warnings(res) == [
        "tracks.jsonl line 2 is cut mid-way: the track it held is left out",
        "tracks.jsonl lacks track 2, which lines of results.jsonl carry: their observations "
        "are left out"]
    assert [o["observationID"] for o in _rows(tmp_path / "pkg" / "observations.csv")
            if o["observationLevel"] == "event"] == ["track-1"]
    assert "damaged (2 cuts); what is whole was written" in res.stderr


def test_tracks_missing_and_a_result_cut_mid_line(tmp_path: Path) -> None:
    run = make_run(tmp_path / "run")
    write_lines(run / "tracks.jsonl", tracks()[:1])  # cut at a line's end: said all the same
    with (run / "results.jsonl").open("a") as f:
        f.write('{"mono_ir": {"timestamp": "')
    res = _export(run, tmp_path / "pkg")
    assert res.exit_code == 1, res.output
    assert _warnings(res) == [
        "results.jsonl line 17 is cut mid-way: that line's result is left out",
        "tracks.jsonl lacks track 2, which lines of results.jsonl carry: their observations "
        "are left out"]
