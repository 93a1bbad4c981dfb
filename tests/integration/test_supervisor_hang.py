"""A worker that hangs on every pair is killed after its pool's timeout_s, each time.

Pins issue 16, item 9: a hung worker lived until supervisor.liveness_s (not its pool's
timeout_s), and a restarted one that hung on its first pair was not killed for 60 s (it took
a pair before its first heartbeat, so the supervisor still counted it as starting).
"""

from __future__ import annotations

import signal
import time
from pathlib import Path

import pytest

from tests.builders import small_source
from tests.conftest import Pipeline, only_pools, poll_for, write_config

pytestmark = pytest.mark.slow  # starts whole pipelines


@pytest.mark.timeout(120)
def test_a_hung_worker_is_killed_after_timeout_s_even_on_its_first_pair(
        spawn, run_dir: Path) -> None:
    cfg = write_config(run_dir.parent / "hang.yaml", {
        "source": small_source(10.0),
        # liveness_s far above timeout_s: only timeout_s can explain a kill within the test
        "supervisor": {"liveness_s": 60.0, "restart_backoff_s": 0.2, "max_restarts": 20},
        "pools": only_pools({
            "hang": {"plugin": "slow", "policy": "latest", "timeout_s": 2.0,
                     "params": {"delay_s": 600.0}},
            "fast": {"plugin": "noop", "policy": "ordered:64"},
        }),
    })
    p: Pipeline = spawn(["--config", str(cfg)], run_dir)

    def restarts() -> int:
        st = p.status()
        if not st:
            return 0
        return int(next(n for n in st["nodes"] if n["name"] == "worker:hang:0")["restarts"])

    poll_for(lambda: restarts() >= 1, 60, interval=0.3, what="the hung worker's first kill")
    t0 = time.monotonic()
    # Restarted workers hang on their first pair: each is killed after about timeout_s
    # (plus its start-up and the back-off), far below liveness_s and the 60 s start-up time.
    poll_for(lambda: restarts() >= 3, 40, interval=0.3, what="two more kills of restarted workers")
    took = time.monotonic() - t0
    assert took < 30, took
    code, out, err = p.stop(signal.SIGINT)
    assert code == 0, err
    assert "silent for" in (run_dir / "trapflow.log").read_text()
