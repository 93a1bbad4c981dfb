"""A source that disappears mid-run (an unplugged disk or camera): capture goes inactive
with the reason, retries with back-off, the rest keeps running, and it resumes."""

from __future__ import annotations

import signal
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import Pipeline, only_pools, poll_for, write_config

pytestmark = pytest.mark.slow  # starts whole pipelines


def _node(status: dict, name: str) -> dict:
    return next(n for n in status["nodes"] if n["name"] == name)


@pytest.mark.timeout(120)
def test_capture_goes_inactive_with_reason_and_recovers(spawn, run_dir: Path) -> None:
    data = run_dir.parent / "cams"
    rng = np.random.default_rng(0)
    for side in ("left", "right"):
        (data / side).mkdir(parents=True)
        for i in range(20):
            img = rng.integers(0, 255, (120, 160, 3), dtype=np.uint8)
            cv2.imwrite(str(data / side / f"{i:04d}.png"), img)
    cfg = write_config(run_dir.parent / "cams.yaml", {
        "source": {"kind": "images", "uri": str(data), "rate_hz": 10.0, "loop": True},
        "pools": only_pools({"fast": {"plugin": "digest", "policy": "ordered:32"}}),
    })
    p: Pipeline = spawn(["--config", str(cfg)], run_dir)
    p.wait_active()
    poll_for(lambda: len(p.results()) > 10, 20, what="pairs from the image folder")
    gone = data.with_name("cams-unplugged")
    data.rename(gone)  # the device disappears
    st = poll_for(lambda: (s := p.status()) and _node(s, "capture")["state"] == "inactive" and s,
                  20, interval=0.2, what="capture inactive")
    reason = _node(st, "capture")["reason"]
    assert "cannot" in reason or "not found" in reason, reason
    assert _node(st, "broker")["state"] == "active"
    assert _node(st, "worker:fast:0")["state"] == "active"
    assert _node(st, "capture")["restarts"] == 0  # the node retries itself; no crash
    gone.rename(data)  # and comes back
    poll_for(lambda: (s := p.status()) and _node(s, "capture")["state"] == "active", 30,
             interval=0.2, what="capture active again")
    n = len(p.results())
    poll_for(lambda: len(p.results()) > n + 10, 20, what="pairs flowing again")
    code, _, err = p.stop(signal.SIGINT)
    assert code == 0, err
