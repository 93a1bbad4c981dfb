"""`trapflow check RUN --against OTHER` (trapflow.export.against): a re-analysis joined to
its live run by capture time, on results files written here line by line."""

from __future__ import annotations

import json
from pathlib import Path

from click.testing import CliRunner

from trapflow.cli.main import main
from trapflow.export.against import check_against


def stamp(i: int) -> str:
    return f"2026-11-29 10:00:{i // 10:02d}.{(i % 10) * 100:03d}"


def lines(seqs: range, *, first_seq: int = 0, shift_ms: int = 0, crab_from: int = 10**9,
          model: str = "3f9c2a1b") -> str:
    out = []
    for n, i in enumerate(seqs):
        t = stamp(i)
        if shift_ms:
            t = t[:-3] + f"{(int(t[-3:]) + shift_ms) % 1000:03d}"
        label = "crab" if i >= crab_from else "none"
        out.append({"mono_ir": {"timestamp": t, "seq": first_seq + n, "label": label,
                                "confidence": 0.9, "box": [] if label == "none" else
                                [1.0, 2.0, 3.0, 4.0], "model": model, "pool": "mono", "v": 3}})
        out.append({"digest": {"timestamp": t, "seq": first_seq + n, "sha": f"{i:08x}",
                               "pool": "d", "v": 3}})
    return "".join(json.dumps(o, separators=(",", ":")) + "\n" for o in out)


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_a_replay_of_the_live_pairs_tells_its_story(tmp_path: Path) -> None:
    live = write(tmp_path / "live.jsonl", lines(range(100, 200), first_seq=100, crab_from=150))
    # The recorder began at pair 120 and the replay numbers from 0; it analysed every pair.
    replay = write(tmp_path / "replay.jsonl", lines(range(120, 180), crab_from=150))
    problems, summary = check_against(live, replay)
    assert problems == []
    assert f"pairs: 60 of the 60 pairs {replay} analysed within the live run's span carry " \
           "a live capture time" in summary
    assert "mono_ir: labels agree on 60 of 60 pairs analysed with the same model" in summary


def test_stamps_off_the_live_capture_times_are_one_disagreement(tmp_path: Path) -> None:
    """The bug of issue 32: results stamped with the image's own time, 1-58 ms off."""
    live = write(tmp_path / "live.jsonl", lines(range(100, 200)))
    off = write(tmp_path / "off.jsonl", lines(range(120, 180), shift_ms=7))
    problems, _ = check_against(live, off)
    assert problems == [f"{off}: 60 of 60 pairs within the live run's span carry no capture "
                        f"time of {live} (at least 99% must)"]


def test_same_model_other_labels_and_a_new_model_that_may_differ(tmp_path: Path) -> None:
    live = write(tmp_path / "live.jsonl", lines(range(100, 200), crab_from=150))
    relabelled = write(tmp_path / "r.jsonl", lines(range(120, 180), crab_from=130))
    problems, _ = check_against(live, relabelled)
    assert len(problems) == 1 and problems[0].startswith(
        "mono_ir: labels differ on 20 of 60 pairs analysed with the same model (first at "
        "2026-11-29 10:00:13.000: live {'none': 1}")
    new_model = write(tmp_path / "m.jsonl", lines(range(120, 180), crab_from=130, model="x"))
    problems, summary = check_against(live, new_model)
    assert problems == [] and "mono_ir: 60 pairs in both, 40 only live, 0 only in " \
                              f"{new_model}" in summary


def test_the_command_checks_the_run_and_its_reanalysis(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    write(run / "results.jsonl", lines(range(100, 140)))
    write(run / "ledger.json", json.dumps({"pools": {
        "mono": {"processed": 40, "kinds": ["mono_ir"]},
        "d": {"processed": 40, "kinds": ["digest"]}}}))
    (tmp_path / "again").mkdir()
    write(tmp_path / "again" / "results.jsonl", lines(range(100, 140), shift_ms=3))
    res = CliRunner().invoke(main, ["check", str(run), "--against", str(tmp_path / "again")])
    assert res.exit_code == 1, res.output
    assert "carry no capture time" in res.output
    write(tmp_path / "again" / "results.jsonl", lines(range(110, 130)))
    res = CliRunner().invoke(main, ["check", str(run), "--against", str(tmp_path / "again")])
    assert res.exit_code == 0, res.output
    assert "tells its story" in res.output
