"""Finite sources with faults, through the real pipeline: bad files are skipped and counted,
the run ends by itself, and its exit status says honestly how it went (issue 12)."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import cv2
import pytest

from tests.builders import NOISE_H as H
from tests.builders import NOISE_W as W
from tests.builders import noise, write_folder, write_recording
from tests.conftest import REPO, Pipeline, write_config

pytestmark = pytest.mark.slow  # starts whole pipelines

def digest(left: Path, right: Path) -> str:
    """The Digest plugin's hash, computed here from the files by OpenCV's own reader."""
    h = hashlib.sha1(cv2.imread(str(left)).tobytes())
    h.update(cv2.imread(str(right)).tobytes())
    return h.hexdigest()[:16]


def pools_config(path: Path, **pools: dict[str, Any]) -> Path:
    return write_config(path, {"pools": pools})


def errors(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("trapflow: error:")]


@pytest.mark.timeout(120)
def test_a_folder_with_bad_files_ends_by_itself_and_counts_each(spawn, run_dir: Path) -> None:
    """Regression (issue 12, item 2): a 0-byte or garbage JPEG, one cut short, or a right
    image of another size stalled the run forever (retried ~15 times a second)."""
    d = run_dir.parent / "pairs"
    write_folder(d, 10)
    (d / "left" / "000002.jpg").write_bytes(b"")
    (d / "right" / "000004.jpg").write_bytes(b"GIF89a but not really an image" * 8)
    cut = d / "left" / "000005.jpg"
    cut.write_bytes(cut.read_bytes()[:-200])
    cv2.imwrite(str(d / "right" / "000007.jpg"), noise(7, 1, W // 2, H // 2))
    bad = {2, 4, 5, 7}
    cfg = pools_config(run_dir.parent / "c.yaml",
                       every={"plugin": "digest", "policy": "ordered:64"})
    p: Pipeline = spawn(["--config", str(cfg), "--workers", "every=1", "--source",
                         f"images:{d}", "--encoding", "raw", "--rate", "20"], run_dir)
    code, out, err = p.wait(90)
    assert code == 0, err
    ledger = json.loads((run_dir / "ledger.json").read_text())
    assert ledger["failed_at_capture"] == 4
    assert ledger["capture_failures"] == {"unreadable": 2, "truncated": 1, "size": 1}
    assert ledger["produced"] == 6 and ledger["pools"]["every"]["processed"] == 6
    assert "4 failed at capture (size 1, truncated 1, unreadable 2)" in out
    # Every good pair processed, in order, with the pixels of its own files.
    got = [r["digest"] for r in p.results()]
    good = [i for i in range(10) if i not in bad]
    assert [r["sha1"] for r in got] == [
        digest(d / "left" / f"{i:06d}.jpg", d / "right" / f"{i:06d}.jpg") for i in good]
    # Each bad file is named once in the log, never again (no retry loop).
    for name in ("left/000002.jpg", "right/000004.jpg", "left/000005.jpg"):
        assert err.count(name) == 1, err
    assert err.count("000007.jpg and right/000007.jpg") == 1, err


@pytest.mark.timeout(90)
def test_a_folder_with_no_readable_pair_fails_with_one_line(spawn, run_dir: Path) -> None:
    d = run_dir.parent / "pairs"
    write_folder(d, 3)
    for i in range(3):
        (d / "left" / f"{i:06d}.jpg").write_bytes(b"")
    p: Pipeline = spawn(["--workers", "vo=1", "--source", f"images:{d}"], run_dir)
    code, _, err = p.wait(60)
    # Found before anything starts, so it is an input error (status 2), named in one line.
    assert code == 2, err
    assert errors(err) == [f"trapflow: error: source images: none of the first 3 left images "
                           f"in {d} can be read"]


@pytest.mark.timeout(90)
def test_a_pool_that_fails_every_pair_fails_the_run(spawn, run_dir: Path) -> None:
    """Regression (issue 12, item 1): vo failed every pair and the run exited 0."""
    d = run_dir.parent / "pairs"
    write_folder(d, 6)
    cfg = pools_config(run_dir.parent / "c.yaml",
                       every={"plugin": "digest", "policy": "ordered:64"},
                       broken={"plugin": "flaky", "policy": "ordered:64",
                               "params": {"every": 1}})
    p: Pipeline = spawn(["--config", str(cfg), "--workers", "every=1,broken=1",
                         "--source", f"images:{d}", "--rate", "20"], run_dir)
    code, _, err = p.wait(60)
    assert code == 1, err
    assert errors(err) == ["trapflow: error: pool broken failed every pair it was given "
                           "(6: WorkerError 6); see trapflow.log"]
    assert len(p.results()) == 6  # the healthy pool's results are all there


@pytest.mark.timeout(90)
def test_a_source_that_cannot_go_on_fails_the_run_with_where(spawn, run_dir: Path) -> None:
    rec = run_dir.parent / "damaged.mcap"
    write_recording(rec, 40, chunk=10)
    data = bytearray(rec.read_bytes())
    data[len(data) // 2 : len(data) // 2 + 64] = bytes(64)
    rec.write_bytes(bytes(data))
    cfg = pools_config(run_dir.parent / "c.yaml",
                       every={"plugin": "digest", "policy": "ordered:64"})
    p: Pipeline = spawn(["--config", str(cfg), "--workers", "every=1", "--size", f"{W}x{H}",
                         "--source", f"replay:{rec}"], run_dir)
    code, _, err = p.wait(60)
    assert code == 1, err
    (line,) = errors(err)
    assert line.startswith("trapflow: error: source replay could not go on: replay: ")
    assert "damaged.mcap is damaged after message" in line
    assert 10 <= len(p.results()) < 40  # the pairs before the damage were processed


def replay(args: list[str], timeout: float = 90) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "trapflow", "replay", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout)


@pytest.mark.timeout(150)
def test_assert_lossless_fails_on_dropped_or_failed_pairs(run_dir: Path) -> None:
    """Regression (issue 12, item 7): --assert-lossless passed with 130 of 175 pairs dropped
    and VO failing 40 of 40, as the final stats showed 0 workers and the check skipped them."""
    work = run_dir.parent
    rec = work / "rec.mcap"
    write_recording(rec, 30)
    cfg = pools_config(work / "c.yaml",
                       every={"plugin": "digest", "policy": "ordered:64"},
                       flaky={"plugin": "flaky", "policy": "ordered:64", "params": {"every": 3}},
                       lagging={"plugin": "slow", "policy": "latest",
                                "params": {"delay_s": 0.2}})
    # At the recorded pace (20 pairs/s) the 0.2 s pool drops; at --rate 0 the replay would
    # wait for it instead (issue 22, item 2: lossless by default).
    bad = replay([str(rec), "--rate", "1", "--assert-lossless", "-c", str(cfg),
                  "--workers", "every=1,flaky=1,lagging=1", "--size", f"{W}x{H}",
                  "--run-dir", str(work / "lossy")])
    assert bad.returncode == 1, bad.stderr + bad.stdout
    (line,) = errors(bad.stderr)
    assert line.startswith("trapflow: error: replay was not lossless: ")
    assert "pool flaky: processed 20 of 30 (dropped 0, failed 10," in line
    assert "pool lagging: processed " in line and "pool every" not in line
    ledger = json.loads((work / "lossy" / "ledger.json").read_text())
    assert ledger["pools"]["lagging"]["dropped_by_policy"] > 0
    # The same recording through the lossless pool alone passes.
    ok = replay([str(rec), "--rate", "0", "--assert-lossless", "-c", str(cfg),
                 "--workers", "every=1", "--size", f"{W}x{H}", "--run-dir", str(work / "ok")])
    assert ok.returncode == 0, ok.stderr + ok.stdout
    assert "pairs read 30, delivered 30" in ok.stdout


@pytest.mark.timeout(90)
def test_pairs_larger_than_the_rig_are_counted(spawn, run_dir: Path) -> None:
    """Regression (issue 12, item 1): with raw pairs, images larger than the ring's slots were
    skipped at capture and appeared nowhere in the totals or the ledger. The ring is sized
    from the source's rig now, so a pair of another size is caught before the ring, as a pair
    that contradicts the rig, and counted as such."""
    d = run_dir.parent / "pairs"
    write_folder(d, 6)
    for side, name in ((0, "left"), (1, "right")):  # pair 3 is four times the slot's size
        cv2.imwrite(str(d / name / "000003.jpg"), noise(3, side, 2 * W, 2 * H))
    cfg = pools_config(run_dir.parent / "c.yaml",
                       every={"plugin": "digest", "policy": "ordered:64"})
    p: Pipeline = spawn(["--config", str(cfg), "--workers", "every=1", "--source",
                         f"images:{d}", "--size", f"{W}x{H}", "--encoding", "raw"], run_dir)
    code, out, err = p.wait(60)
    assert code == 0, err
    ledger = json.loads((run_dir / "ledger.json").read_text())
    assert ledger["capture_failures"] == {"geometry": 1}
    assert ledger["produced"] == 5 and ledger["pools"]["every"]["processed"] == 5
    assert "1 failed at capture (geometry 1)" in out
    assert err.count("pair skipped") == 1
