"""runs/latest moves when a run starts, and only then (issue 22, item 7: see also
tests/unit/test_failed_start.py for the start that fails)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.builders import write_folder
from tests.conftest import REPO, only_pools, write_config


@pytest.mark.timeout(120)
def test_a_run_that_starts_takes_runs_latest(run_dir: Path) -> None:
    # A short folder: runs/<timestamp>/capture.sock must fit the 107 bytes of a socket path
    # (pytest's tmp_path under a parallel worker is too long).
    tmp_path = run_dir.parent
    write_folder(tmp_path / "pairs", 3)
    runs = tmp_path / "runs"
    (runs / "20260101-000000-000").mkdir(parents=True)
    (runs / "latest").symlink_to("20260101-000000-000")
    cfg = write_config(tmp_path / "c.yaml", {"pools": only_pools({"d": {"plugin": "digest"}})})
    path = os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)
    out = subprocess.run(
        [sys.executable, "-m", "trapflow", "start", "--config", str(cfg), "--source",
         f"images:{tmp_path / 'pairs'}", "--rate", "20"],
        cwd=tmp_path, env={**os.environ, "PYTHONPATH": path}, capture_output=True, text=True,
        timeout=100)
    assert out.returncode == 0, out.stderr
    new = sorted(p.name for p in runs.iterdir() if p.name not in ("latest",
                                                                  "20260101-000000-000"))
    assert len(new) == 1 and os.readlink(runs / "latest") == new[0]
    assert len((runs / "latest" / "results.jsonl").read_text().splitlines()) == 3
