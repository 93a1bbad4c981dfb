"""`trapflow record` stops by itself: when the pipeline it records ends (with what the
pipeline published last in the file) and after `--duration`."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
from rosbags.highlevel import AnyReader

from tests.conftest import REPO, Pipeline, poll_for

pytestmark = pytest.mark.slow  # starts whole pipelines


def _recorder(run_dir: Path, out: Path, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "trapflow", "record", "--run-dir", str(run_dir), "-o", str(out),
         *args], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _recorded_seqs(rec: Path) -> set[int]:
    with AnyReader([rec]) as reader:
        conns = [c for c in reader.connections if c.topic.startswith("/trapflow/results/")]
        return {body["seq"] for c, _, raw in reader.messages(connections=conns)
                for body in json.loads(reader.deserialize(raw, c.msgtype).data).values()}


@pytest.mark.timeout(150)
def test_the_recorder_ends_with_its_pipeline_and_keeps_the_last_results(
        spawn, run_dir: Path) -> None:
    """Regression (issue 22 item 6): `trapflow record` kept running after its pipeline
    ended, until someone pressed Ctrl-C."""
    rec = run_dir.parent / "field.mcap"
    p: Pipeline = spawn(["--workers", "noop=1", "--size", "160x120", "--rate", "10"],
                        run_dir)
    p.wait_active(90)
    recorder = _recorder(run_dir, rec)
    try:
        poll_for(lambda: (rec.parent / "field.mcap.part").exists(), 30,
                 what="the recorder writing")
        time.sleep(1.0)  # some results recorded
        # Ended once the recorder records (a fixed --duration could end it before a slow
        # start of the recorder on a loaded machine, and the test would wait in vain).
        code, _out, err = p.stop(timeout=60)
        assert code == 0, err
        out, err = recorder.communicate(timeout=30)  # by itself: no signal sent
    finally:
        if recorder.poll() is None:
            recorder.kill()
            recorder.wait(10)
    assert recorder.returncode == 0, err
    assert "until the pipeline ends" in err and "pairs, results: noop" in out, (out, err)
    assert rec.exists() and not (rec.parent / "field.mcap.part").exists()
    last = json.loads((run_dir / "results.jsonl").read_text().splitlines()[-1])
    (body,) = last.values()
    assert body["seq"] in _recorded_seqs(rec)  # the pipeline's last result is in the file


@pytest.mark.timeout(150)
def test_the_recorder_stops_after_its_duration(spawn, run_dir: Path) -> None:
    """Regression (issue 22 item 6): `trapflow record` had no `--duration`."""
    rec = run_dir.parent / "short.mcap"
    p: Pipeline = spawn(["--workers", "noop=1", "--size", "160x120", "--rate", "10"], run_dir)
    p.wait_active(90)
    t0 = time.monotonic()
    recorder = _recorder(run_dir, rec, "--duration", "2")
    try:
        out, err = recorder.communicate(timeout=40)
    finally:
        if recorder.poll() is None:
            recorder.kill()
            recorder.wait(10)
    assert recorder.returncode == 0, err
    assert time.monotonic() - t0 < 30
    assert p.proc.poll() is None  # the pipeline goes on
    assert rec.exists() and _recorded_seqs(rec), out
    p.stop()
