"""A start that fails before capture leaves no run behind: no run directory of its own, and
runs/latest still names the last run that started (nothing is spawned in these tests)."""

from __future__ import annotations

import os
import socket
from collections.abc import Callable
from pathlib import Path

import pytest
from click.testing import CliRunner

from trapflow.cli.main import main
from trapflow.supervisor.setup import LOCK_FILE, discard_run_dir


def _garbage(root: Path) -> Path:
    """A folder of left/right "images" that no reader can decode."""
    for side in ("left", "right"):
        (root / side).mkdir(parents=True)
        for i in range(3):
            (root / side / f"{i:06d}.png").write_bytes(b"not an image at all" * (i + 1))
    return root


def _start(cwd: Path, *args: str) -> tuple[int, str]:
    old = Path.cwd()
    os.chdir(cwd)  # runs/ is relative to where trapflow is started
    try:
        res = CliRunner().invoke(main, ["start", "--source", f"images:{cwd / 'imgs'}",
                                        "--duration", "1", *args])
    finally:
        os.chdir(old)
    return res.exit_code, res.output


def test_a_failed_start_leaves_runs_latest_and_no_run_directory(tmp_path: Path) -> None:
    """Regression (issue 22, item 7): a folder of garbage images exited 2 but left an empty
    run directory and pointed runs/latest at it, so the next report, export or status read
    it instead of the last real run."""
    _garbage(tmp_path / "imgs")
    runs = tmp_path / "runs"
    (runs / "20260101-000000-000").mkdir(parents=True)
    (runs / "latest").symlink_to("20260101-000000-000")
    code, out = _start(tmp_path)
    assert code == 2, out
    assert "none of the first 3 left images" in out
    assert sorted(p.name for p in runs.iterdir()) == ["20260101-000000-000", "latest"]
    assert os.readlink(runs / "latest") == "20260101-000000-000"


def test_a_failed_start_removes_the_run_dir_it_created_and_keeps_one_it_did_not(
        tmp_path: Path) -> None:
    _garbage(tmp_path / "imgs")
    code, _ = _start(tmp_path, "--run-dir", str(tmp_path / "new" / "run"))
    assert code == 2 and not (tmp_path / "new" / "run").exists()
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("kept\n")
    code, _ = _start(tmp_path, "--run-dir", str(mine))
    assert code == 2 and (mine / "notes.txt").read_text() == "kept\n"
    assert not (tmp_path / "runs").exists()  # no latest for a run directory given by name


def _lock(d: Path) -> None:
    (d / LOCK_FILE).write_text("123")


def _sock(d: Path) -> None:
    with socket.socket(socket.AF_UNIX) as s:
        s.bind(str(d / "control.sock"))


def _empty_log(d: Path) -> None:
    (d / "trapflow.log").write_bytes(b"")


def _log(d: Path) -> None:
    (d / "trapflow.log").write_text("worker:vo:0 cannot start: ...\n")


def _sub(d: Path) -> None:
    (d / "events").mkdir()


@pytest.mark.parametrize(("fill", "removed"), [
    ([], True),  # nothing at all
    ([_lock, _sock, _empty_log], True),  # what a start that failed early leaves
    ([_lock, _log], False),  # a log that says why: the user is pointed at it
    ([_lock, _sub], False),  # a folder: not ours to judge
])
def test_discard_run_dir_removes_only_a_directory_of_no_value(
        tmp_path: Path, fill: list[Callable[[Path], None]], removed: bool) -> None:
    d = tmp_path / "run"
    d.mkdir()
    for f in fill:
        f(d)
    assert discard_run_dir(d) is removed
    assert d.exists() is not removed
