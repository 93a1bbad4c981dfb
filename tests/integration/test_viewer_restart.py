"""A viewer that dies is restarted, and one that keeps dying is given up on while the
pipeline goes on: the viewer is never essential to the trap."""

from __future__ import annotations

import signal
from pathlib import Path

import psutil
import pytest

from tests.conftest import Pipeline, poll_for, write_config
from tests.integration.viewer_util import free_port, get_json, use_token

pytestmark = pytest.mark.slow  # starts whole pipelines


def _viewer(p: Pipeline) -> psutil.Process | None:
    for kid in p.track():
        try:
            if kid.cmdline()[:1] == ["trapflow:viewer"]:
                return kid
        except psutil.Error:
            continue
    return None


def _node(p: Pipeline, name: str) -> dict | None:
    s = p.status()
    return next((n for n in s["nodes"] if n["name"] == name), None) if s else None


@pytest.mark.timeout(150)
def test_a_crashing_viewer_never_stops_the_pipeline(spawn, run_dir: Path) -> None:
    """Regression: the supervisor treated every role but workers as essential, so a viewer
    past its restart budget would have stopped the whole run."""
    cfg = write_config(run_dir.parent / "one-restart.yaml",
                       {"supervisor": {"max_restarts": 1, "restart_window_s": 600}})
    port = free_port()
    use_token(port, run_dir)
    url = f"http://127.0.0.1:{port}/api/state"
    p: Pipeline = spawn(["--config", str(cfg), "--size", "320x240", "--workers", "vo=1",
                         "--view", str(port)], run_dir)
    p.wait_active(90)
    first = poll_for(lambda: _viewer(p), 10, what="the viewer process")
    first.send_signal(signal.SIGKILL)
    poll_for(lambda: (n := _node(p, "viewer")) and n["restarts"] == 1 and n["state"] == "active",
             30, interval=0.3, what="the viewer restarted once")
    poll_for(lambda: (s := get_json(url)) and s["nodes"], 20, interval=0.3,
             what="the restarted viewer's page")
    second = poll_for(lambda: (v := _viewer(p)) and v.pid != first.pid and v, 10,
                      what="the new viewer process")
    second.send_signal(signal.SIGKILL)
    poll_for(lambda: (n := _node(p, "viewer")) and "gave up" in n["reason"], 30, interval=0.3,
             what="the supervisor giving up on the viewer")
    before = p.status()["stats"]["pools"]["vo"]["processed"]
    poll_for(lambda: p.status()["stats"]["pools"]["vo"]["processed"] > before + 5, 20,
             interval=0.5, what="the pipeline going on without its viewer")
    assert p.proc.poll() is None
    code, _, err = p.stop()
    assert code == 0, err
