"""`trapflow check RUN_DIR` on small run directories made by hand: one whose files agree,
and one each with a result line deleted, a track renamed and a count changed, each found
as one line naming the file, the line or id, and both numbers."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import REPO
from tests.unit.made_run import counts, make_run, results, stamp, t_of, tracks, write_lines
from trapflow.export.check import check_run


def test_a_run_whose_files_agree(tmp_path: Path) -> None:
    assert check_run(make_run(tmp_path / "run")) == []


def test_a_result_line_deleted(tmp_path: Path) -> None:
    run = make_run(tmp_path / "run")
    lines = [r for r in results() if r.get("mono_ir", {}).get("seq") != 5]
    write_lines(run / "results.jsonl", lines)
    assert check_run(run) == [
        "ledger.json pool mono: processed 8, results.jsonl has 7 distinct seqs of mono_ir"]


def test_a_track_renamed(tmp_path: Path) -> None:
    run = make_run(tmp_path / "run")
    renamed = tracks()
    renamed[1]["track"]["id"] = 9
    write_lines(run / "tracks.jsonl", renamed)
    # Track 2's first line: seq 7's detection, the 13th line (mono and VO lines alternate).
    assert check_run(run) == ["results.jsonl line 13: track 2 (2 lines) is not in tracks.jsonl"]


def test_a_count_changed(tmp_path: Path) -> None:
    run = make_run(tmp_path / "run")
    changed = counts()
    changed[0]["counts"]["labels"][0]["max_n"] = 2
    write_lines(run / "counts.jsonl", changed)
    assert check_run(run) == [
        "counts.jsonl line 1 (2026-11-28 10:00:00): crab max_n 2, the tracks imply 1"]


def test_a_track_relabelled_and_lines_outside_its_span(tmp_path: Path) -> None:
    run = make_run(tmp_path / "run")
    moved = tracks()
    moved[0]["track"]["label"] = "scallop"  # and so the interval's visits per label differ
    moved[1]["track"]["first_s"] += 1.0  # seq 6 and 7 now lie before it
    write_lines(run / "tracks.jsonl", moved)
    got = check_run(run)
    assert "tracks.jsonl line 1: track 1 is scallop, but 0 of its 2 lines in results.jsonl " \
           "say scallop and 2 say crab" in got
    assert any(g.startswith("results.jsonl line 13: track 2 at ") and "outside its span" in g
               for g in got), got
    assert "counts.jsonl line 1 (2026-11-28 10:00:00): crab visits 2, the tracks imply 1" in got


def test_a_cut_last_line_and_an_unpaired_kind(tmp_path: Path) -> None:
    run = make_run(tmp_path / "run")
    with (run / "results.jsonl").open("a") as f:
        f.write(json.dumps({"tags": {"timestamp": stamp(9), "seq": 9, "corners": []}}) + "\n")
        f.write('{"mono_ir": {"timestamp": "2026-')
    assert check_run(run) == [
        "results.jsonl line 18 is cut mid-way: it holds no whole line there",
        "results.jsonl: 1 seqs of tags, which no pool of ledger.json made"]


def test_a_surface_file_against_the_run(tmp_path: Path) -> None:
    run = make_run(tmp_path / "run")
    heard = [{"new_label": {"label": "crab", "time": stamp(3)[:19], "track": 1}},
             {"mono_ir": {"timestamp": stamp(3), "seq": 3, "label": "crab", "track": 1}},
             {"track": {"id": 1, "label": "crab", "start": stamp(2)[:19], "duration_s": 1}},
             {"counts": {"start": "2026-11-28 10:00:00", "minutes": 0, "pairs": 8, "labels": [
                 {"label": "crab", "visits": 2, "max_n": 1, "dwell_s": 2}]}},
             {"health": {"uptime_s": 5}},
             {"aggregate": {"class": "mono_ir/*", "count": 2, "best": [
                 {"mono_ir": {"timestamp": stamp(3), "seq": 3, "label": "crab",
                              "track": 1}}]}}]
    write_lines(tmp_path / "surface.jsonl", heard)
    assert check_run(run, surface=tmp_path / "surface.jsonl") == []
    heard[1]["mono_ir"]["track"] = 2
    heard[2]["track"]["label"] = "scallop"
    heard[5]["aggregate"]["best"][0]["mono_ir"]["label"] = "fish"
    write_lines(tmp_path / "surface.jsonl", heard)
    assert check_run(run, surface=tmp_path / "surface.jsonl") == [
        f"surface surface.jsonl line 2: mono_ir seq 3 (timestamp {stamp(3)}, label crab, "
        "track 2) is no line of results.jsonl",
        f"surface surface.jsonl line 3: track 1 scallop from {stamp(2)[:19]}, tracks.jsonl "
        f"has crab from {stamp(2)[:19]}",
        f"surface surface.jsonl line 6: an aggregate's best mono_ir seq 3 (timestamp "
        f"{stamp(3)}, label fish, track 1) is no line of results.jsonl"]


def _digest(seq: int, pool: str | None) -> dict[str, Any]:
    body: dict[str, Any] = {"timestamp": stamp(seq), "seq": seq, "hex": "ab"}
    return {"digest": {**body, "pool": pool, "v": 3} if pool else {**body, "v": 2}}


def _two_pools(run: Path, lines: list[dict[str, Any]], local: int, remote: int,
               **ledger: Any) -> None:
    """The made run with two pools of one plugin (a local and a remote digest pool)."""
    write_lines(run / "results.jsonl", results() + lines)
    led = json.loads((run / "ledger.json").read_text())
    pool = {**led["pools"]["vo"], "kinds": ["digest"]}
    led["pools"].update(hash={**pool, "processed": local},
                        hash_remote={**pool, "processed": remote})
    (run / "ledger.json").write_text(json.dumps({**led, **ledger}))


def test_two_pools_of_one_plugin_each_credited_their_own_lines(tmp_path: Path) -> None:
    """Regression (issue 32): every line of a kind was credited to one pool (the last the
    normalizer routed), so two pools of one plugin never agreed with the ledger. A line
    names its pool: each pool is held to its own lines, a seq both processed counted once
    for each; a line of a pool the ledger lacks is a disagreement."""
    run = make_run(tmp_path / "run")
    lines = [_digest(s, "hash") for s in range(1, 9)] + [_digest(s, "hash_remote")
                                                         for s in (2, 4, 6)]
    _two_pools(run, lines, 8, 3)
    assert check_run(run) == []
    _two_pools(run, lines[:-1] + [_digest(6, "hash_spare")], 8, 3)
    assert check_run(run) == [
        "ledger.json pool hash_remote: processed 3, results.jsonl has 2 distinct seqs of "
        "digest",
        "results.jsonl: 1 seqs of pool hash_spare, which ledger.json does not have"]


def test_lines_naming_no_pool_are_credited_by_kind(tmp_path: Path) -> None:
    """A run from before lines named their pool: its lines are credited by kind, to the one
    pool whose `kinds` list it (the made run's lines name none); a kind two pools list
    cannot be credited, and says so."""
    run = make_run(tmp_path / "run")
    _two_pools(run, [_digest(s, None) for s in range(1, 4)], 3, 0)
    assert check_run(run) == [
        "ledger.json pool hash: processed 3, results.jsonl has 0 distinct seqs of digest",
        "results.jsonl: 3 seqs of digest, which name no pool, and pools hash, hash_remote "
        "all make digest"]


def test_a_later_start_is_held_to_its_own_lines(tmp_path: Path) -> None:
    """A run directory started again (after a power cut): results.jsonl holds both starts'
    lines, ledger.json counts the last start's, from the byte it names (`results_from`);
    the tracks and counts checks read every line."""
    run = make_run(tmp_path / "run")
    first = (run / "results.jsonl").read_bytes()
    later = [_digest(s, "hash") for s in range(20, 25)]
    _two_pools(run, later, 5, 0, results_from=len(first))
    (run / "results.jsonl").write_bytes(first + b"".join(
        json.dumps(o).encode() + b"\n" for o in later))
    led = json.loads((run / "ledger.json").read_text())
    led["pools"]["mono"]["processed"] = led["pools"]["vo"]["processed"] = 0  # not this start
    (run / "ledger.json").write_text(json.dumps(led))
    assert check_run(run) == []
    led["pools"]["hash"]["processed"] = 6
    (run / "ledger.json").write_text(json.dumps(led))
    assert check_run(run) == [
        "ledger.json pool hash: processed 6, results.jsonl has 5 distinct seqs of digest from "
        "line 17 (this start's)"]


def test_a_later_start_numbers_its_pairs_again(tmp_path: Path) -> None:
    """Regression (issue 32): a run started again in its run directory numbers its pairs from
    0 again, so one seq named two pairs, and the check counted both pairs' tracks as on one
    pair: 'crab max_n 2, the tracks imply 4' on a power-cut run whose counts were right."""
    run = make_run(tmp_path / "run")
    shift = 10 * 0.5  # the second start's pairs: seqs 1-8 again, 5 s later, tracks 3 and 4
    again = []
    for obj in results():
        (kind, body), = obj.items()
        t = t_of(body["seq"]) + shift
        body = {**body, "timestamp": stamp(body["seq"] + 10)}
        if isinstance(body.get("track"), int):
            body["track"] += 2
        assert abs(t - t_of(body["seq"] + 10)) < 1e-9
        again.append({kind: body})
    first = (run / "results.jsonl").read_bytes()
    write_lines(run / "results.jsonl", results() + again)
    later = [{"track": {**t["track"], "id": t["track"]["id"] + 2,
                        "first_s": round(t["track"]["first_s"] + shift, 3),
                        "last_s": round(t["track"]["last_s"] + shift, 3)}} for t in tracks()]
    write_lines(run / "tracks.jsonl", tracks() + later)
    c = counts()
    c[0]["counts"]["end_s"] = round(t_of(18), 3)
    c[0]["counts"]["labels"][0]["visits"] = 4
    write_lines(run / "counts.jsonl", c)
    led = json.loads((run / "ledger.json").read_text())
    (run / "ledger.json").write_text(json.dumps({**led, "results_from": len(first)}))
    assert check_run(run) == []


def _check(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "trapflow", "check", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=60)


@pytest.mark.timeout(120)
def test_the_command_exits_0_1_or_2(tmp_path: Path) -> None:
    run = make_run(tmp_path / "run")
    res = _check(str(run))
    assert res.returncode == 0 and "its files agree" in res.stdout, res.stderr
    write_lines(run / "counts.jsonl", [])
    res = _check(str(run))
    assert res.returncode == 1
    assert res.stdout.splitlines() == [
        f"tracks.jsonl line {n}: track {n} first seen at {t:.3f}, in no interval of "
        "counts.jsonl" for n, t in ((1, t_of(3)), (2, t_of(7)))]
    assert "trapflow: error: check: " in res.stderr
    # A run still going: its supervisor's lock names a live process (this test's own).
    (run / "supervisor.lock").write_text(str(os.getpid()))
    res = _check(str(run))
    assert res.returncode == 2 and "a run still going" in res.stderr, res.stderr
    res = _check(str(tmp_path / "nowhere"))
    assert res.returncode == 2 and "no directory" in res.stderr, res.stderr
