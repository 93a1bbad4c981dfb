"""`trapflow record --run-dir runs/latest` while `trapflow start` brings a new pipeline up
beside the last run: it waits for runs/latest to name the new run and records that one.

Regression: record resolved runs/latest at once, to the last run (stopped), and waited
there forever for a pipeline that would never come, recording nothing. The new pipeline
takes its time to start here (a pool that sleeps 15 s in configure), so record looks while
runs/latest still names the old run.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from rosbags.highlevel import AnyReader

from tests.conftest import REPO, only_pools, poll_for, write_config

pytestmark = pytest.mark.slow  # starts a whole pipeline


@pytest.mark.timeout(240)
def test_record_of_runs_latest_waits_for_the_pipeline_that_starts(run_dir: Path) -> None:
    work = run_dir.parent  # short: runs/<timestamp>/*.sock must fit a socket path
    runs = work / "runs"
    old = runs / "20260101-000000-000"
    old.mkdir(parents=True)
    (old / "results.jsonl").write_text("")
    (runs / "latest").symlink_to(old.name)
    cfg = write_config(work / "c.yaml", {"pools": only_pools({"s": {
        "plugin": "tests.integration.record_plugins:SlowStart", "params": {"start_s": 15}}})})
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)}
    start = subprocess.Popen(
        [sys.executable, "-m", "trapflow", "start", "--config", str(cfg), "--size", "160x120",
         "--rate", "10", "--duration", "8"],
        cwd=work, env=env, start_new_session=True, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True)
    try:
        new = poll_for(lambda: [p for p in runs.iterdir() if (p / "supervisor.lock").exists()],
                       60, what="the new pipeline holding its run directory")[0]
        rec = subprocess.run(
            [sys.executable, "-m", "trapflow", "record", "--run-dir", "runs/latest", "-o",
             "field.mcap", "--wait", "90"],
            cwd=work, env=env, capture_output=True, text=True, timeout=180)
        _out, err = start.communicate(timeout=60)
        code = start.returncode
    finally:
        if start.poll() is None:
            os.killpg(start.pid, signal.SIGKILL)
            start.wait(10)
    assert code == 0, err
    assert rec.returncode == 0, rec.stderr
    assert f"runs/latest names a stopped run ({old})" in rec.stderr, rec.stderr
    assert os.readlink(runs / "latest") == new.name
    with AnyReader([work / "field.mcap"]) as reader:
        pairs = [c for c in reader.connections if c.topic == "/trapflow/pairs"]
        assert pairs and sum(c.msgcount for c in pairs) > 0
