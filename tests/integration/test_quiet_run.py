"""A plain run says nothing misleading: no WARNING in its log from start to a normal stop
(a CPU-only onnxruntime, a pool grown at run time, workers and links closing at the stop
included), and its run directory keeps no socket file and no lock after exit 0."""

from __future__ import annotations

import stat
import subprocess
import sys
from pathlib import Path

import pytest

from tests.builders import small_source
from tests.conftest import REPO, Pipeline, only_pools, write_config

pytestmark = pytest.mark.slow  # starts a whole pipeline


@pytest.mark.timeout(180)
def test_a_normal_run_logs_no_warning_and_leaves_no_socket_or_lock(spawn, run_dir: Path
                                                                   ) -> None:
    """Regression (issue 22 item 9): every start on a CPU-only machine warned about
    TensorRT/CUDA; a worker added at run time logged "WARNING restarting worker"; a normal
    stop logged "evicted worker ... (stopping)" and "results link: local link closed by its
    peer; reconnecting"; the run directory kept its socket files and supervisor.lock."""
    cfg = write_config(run_dir.parent / "quiet.yaml", {
        "source": small_source(8.0, seed=3),
        "pools": only_pools({"mono": {"count": 1, "policy": "latest"},  # ONNX, on CPU here
                             "vo": {"count": 1}})})
    p: Pipeline = spawn(["--config", str(cfg), "--duration", "6"], run_dir)
    p.wait_active(90)
    grow = subprocess.run([sys.executable, "-m", "trapflow", "pool", "mono", "--count", "2",
                           "--run-dir", str(run_dir)], capture_output=True, text=True,
                          timeout=30, cwd=REPO, check=False)
    assert grow.returncode == 0, grow.stderr
    code, _out, err = p.wait(90)
    assert code == 0, err
    log = (run_dir / "trapflow.log").read_text()
    assert "starting worker:mono:1" in log  # the pool did grow during the run
    # A segment another run left in /dev/shm is this machine's past, not this run's doing.
    noise = [line for line in log.splitlines()
             if (" WARNING " in line and "stale shared-memory segment" not in line)
             or "closed by its peer" in line or ("evicted worker" in line and " INFO " in line)]
    assert not noise, "\n".join(noise)
    left = [path.name for path in run_dir.iterdir()
            if stat.S_ISSOCK(path.lstat().st_mode) or path.name == "supervisor.lock"]
    assert not left, left
