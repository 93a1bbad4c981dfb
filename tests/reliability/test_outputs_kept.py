"""No command destroys data on a plausible mistake (docs/cli.md, "Outputs"): the real CLI,
as a subprocess, on outputs that are already there, outputs that are an input, and outputs
in a folder that is not there. Every refusal is one line and status 2, and the file is
left byte for byte as it was. And `trapflow record` attaches only to a pipeline that runs:
a stopped run is refused, a starting one is waited for a bounded time.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from tests.conftest import REPO
from tests.unit.made_run import make_run

TIMEOUT_S = 60
DATA = bytes(range(256)) * 8  # what must survive, byte for byte


def trapflow(*args: str | Path, cwd: Path = REPO,
             timeout: float = TIMEOUT_S) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "trapflow", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=timeout)


def refused(res: subprocess.CompletedProcess[str], *words: str) -> str:
    """The one error line of a command that exited 2 before writing; it has every word."""
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)
    assert len(lines) == 1 and lines[0].startswith("trapflow: error: "), res.stderr
    assert "Traceback" not in res.stderr
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


def kept(path: Path) -> Path:
    path.write_bytes(DATA)
    return path


DETECTIONS = "".join(f"{f},-1,{100 + 2 * f},50,40,30,0.9\n" for f in range(1, 11))


def _record(d: Path) -> tuple[list[str | Path], Path]:
    return ["record", "--run-dir", d / "no-run", "-o", kept(d / "field.mcap")], d / "field.mcap"


def _record_part(d: Path) -> tuple[list[str | Path], Path]:
    # The .part of a recording cut short: `trapflow recover` could still make it whole.
    return (["record", "--run-dir", d / "no-run", "-o", d / "field.mcap"],
            kept(d / "field.mcap.part"))


def _track(d: Path) -> tuple[list[str | Path], Path]:
    (d / "det.txt").write_text(DETECTIONS)
    return ["track", d / "det.txt", "-o", kept(d / "tracks.txt"), "--fps", "10"], d / "tracks.txt"


def _track_counts(d: Path) -> tuple[list[str | Path], Path]:
    (d / "det.txt").write_text(DETECTIONS)
    return (["track", d / "det.txt", "-o", d / "tracks.txt", "--fps", "10"],
            kept(d / "tracks.counts.jsonl"))


def _calibrate(d: Path) -> tuple[list[str | Path], Path]:
    # Refused before any image is looked at (there are none here).
    return (["calibrate", f"{d}/L*.png", f"{d}/R*.png", "-o", kept(d / "calib.yaml")],
            d / "calib.yaml")


def _recover(d: Path) -> tuple[list[str | Path], Path]:
    return ["recover", kept(d / "rec.mcap.part"), "-o", kept(d / "rec.mcap")], d / "rec.mcap"


def _report(d: Path) -> tuple[list[str | Path], Path]:
    run = make_run(d / "run")
    return ["report", run], kept(run / "report.html")


def _camtrapdp(d: Path) -> tuple[list[str | Path], Path]:
    run = make_run(d / "run")
    (d / "pkg").mkdir()
    return (["export", "camtrapdp", run, d / "pkg", "--latitude", "50", "--longitude", "-4"],
            kept(d / "pkg" / "datapackage.json"))


def _synth(d: Path) -> tuple[list[str | Path], Path]:
    (d / "ds").mkdir()
    return (["dataset", "synth", d / "ds", "--frames", "1", "--width", "64", "--height", "48"],
            kept(d / "ds" / "mine.txt"))


def _modem_sim(d: Path) -> tuple[list[str | Path], Path]:
    return ["modem-sim", "--link-a", kept(d / "box")], d / "box"


def _tap(d: Path) -> tuple[list[str | Path], Path]:
    (d / "frames").mkdir()
    return (["tap", "frames", "--save-frames", d / "frames", "--endpoint", f"ipc://{d}/none",
             "--timeout", "0.2"], kept(d / "frames" / "00000001_left.jpg"))


@pytest.mark.timeout(4 * TIMEOUT_S)
@pytest.mark.parametrize("case", [_record, _record_part, _track, _track_counts, _calibrate,
                                  _recover, _report, _camtrapdp, _synth, _modem_sim, _tap],
                         ids=lambda f: f.__name__.strip("_"))
def test_an_output_that_is_there_is_kept(
        tmp_path: Path, case: Callable[[Path], tuple[list[str | Path], Path]]) -> None:
    args, path = case(tmp_path)
    before = sorted(os.listdir(path.parent))
    line = refused(trapflow(*args), "exists", "--force")
    assert path.name in line or f"{path.parent.name} exists and is not empty" in line
    assert path.read_bytes() == DATA
    assert sorted(os.listdir(path.parent)) == before  # no half file beside it either


@pytest.mark.timeout(4 * TIMEOUT_S)
def test_track_replaces_its_output_only_with_force_and_never_its_input(tmp_path: Path) -> None:
    det = tmp_path / "det.txt"
    det.write_text(DETECTIONS)
    (tmp_path / "same.txt").hardlink_to(det)
    for out in (det, tmp_path / "same.txt"):
        refused(trapflow("track", det, "-o", out, "--fps", "10", "--force"),
                "is also an input", "DETECTIONS")
        assert det.read_text() == DETECTIONS
    refused(trapflow("track", det, "-o", tmp_path / "t.txt", "--counts", det, "--fps", "10"),
            "--counts", "is also an input")
    assert det.read_text() == DETECTIONS
    out = kept(tmp_path / "tracks.txt")
    res = trapflow("track", det, "-o", out, "--fps", "10", "--force")
    assert res.returncode == 0, res.stderr
    assert out.read_text().startswith("2,1,")  # the first row is tentative, not written


@pytest.mark.timeout(4 * TIMEOUT_S)
def test_an_input_is_never_an_output_even_with_force(tmp_path: Path) -> None:
    image = kept(tmp_path / "L1.png")
    refused(trapflow("calibrate", f"{tmp_path}/L*.png", f"{tmp_path}/R*.png", "-o", image,
                     "--force"), "is also an input", "LEFT_GLOB")
    run = make_run(tmp_path / "run")
    results = (run / "results.jsonl").read_bytes()
    refused(trapflow("report", run, "-o", run / "results.jsonl", "--force"), "is also an input")
    refused(trapflow("export", "camtrapdp", run, run, "--latitude", "50", "--longitude", "-4",
                     "--force"), "is also an input")
    refused(trapflow("export", "camtrapdp", run, tmp_path, "--latitude", "50", "--longitude",
                     "-4", "--force"), "holds an input")
    assert image.read_bytes() == DATA and (run / "results.jsonl").read_bytes() == results


@pytest.mark.timeout(4 * TIMEOUT_S)
def test_a_missing_folder_is_one_line(tmp_path: Path) -> None:
    (tmp_path / "det.txt").write_text(DETECTIONS)
    refused(trapflow("track", tmp_path / "det.txt", "-o", tmp_path / "no" / "t.txt", "--fps",
                     "10"), "the folder", "is not there")
    refused(trapflow("record", "--run-dir", tmp_path, "-o", tmp_path / "no" / "f.mcap"),
            "the folder", "is not there")
    assert sorted(os.listdir(tmp_path)) == ["det.txt"]


# --- record attaches only to a pipeline that runs --------------------------------------


@pytest.fixture
def live_pid() -> Iterator[int]:
    """A live process that is no supervisor: what a run directory's lock names while its
    supervisor starts (before its control socket answers)."""
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    yield proc.pid
    proc.kill()
    proc.wait(10)


def _stopped_run(path: Path) -> Path:
    path.mkdir(parents=True)
    (path / "results.jsonl").write_text("")  # what a run that ended leaves: no lock
    return path


@pytest.mark.timeout(4 * TIMEOUT_S)
def test_record_refuses_a_run_that_has_stopped(tmp_path: Path) -> None:
    run = _stopped_run(tmp_path / "runs" / "20261128-101010-000")
    (tmp_path / "runs" / "latest").symlink_to(run.name)
    for named in (run, tmp_path / "runs" / "latest"):
        t0 = time.monotonic()
        refused(trapflow("record", "--run-dir", named, "-o", tmp_path / "f.mcap"),
                "no pipeline runs in", "has stopped")
        assert time.monotonic() - t0 < TIMEOUT_S / 2  # at once: nothing to wait for
    refused(trapflow("record", "--run-dir", tmp_path / "nothing", "-o", tmp_path / "f.mcap"),
            "no run directory")
    assert not list(tmp_path.glob("f.mcap*"))


@pytest.mark.timeout(4 * TIMEOUT_S)
def test_record_waits_a_bounded_time_for_a_starting_pipeline(tmp_path: Path,
                                                             live_pid: int) -> None:
    starting = tmp_path / "runs" / "20261128-121212-000"
    starting.mkdir(parents=True)
    (starting / "supervisor.lock").write_text(str(live_pid))
    res = trapflow("record", "--run-dir", starting, "-o", tmp_path / "f.mcap", "--wait", "1")
    assert "is starting; waiting for it (up to 1 s" in res.stderr, res.stderr
    assert res.stderr.strip().splitlines()[-1].startswith("trapflow: error: ")
    assert res.returncode == 2 and "no pipeline answered there within 1 s" in res.stderr
    # runs/latest still names the run before; the one starting beside it is waited for.
    old = _stopped_run(tmp_path / "runs" / "20261128-101010-000")
    (tmp_path / "runs" / "latest").symlink_to(old.name)
    res = trapflow("record", "--run-dir", tmp_path / "runs" / "latest", "-o",
                   tmp_path / "f.mcap", "--wait", "1")
    assert res.returncode == 2, res.stderr
    assert f"names a stopped run ({old})" in res.stderr and str(starting) in res.stderr
    assert not list(tmp_path.glob("f.mcap*"))
