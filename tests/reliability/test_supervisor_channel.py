"""A process of the pipeline's own user cannot speak for the supervisor to the broker.

Pins issue 26 item 9: the supervisor's orders rode the workers socket under the identity
`supervisor`; after a broker restart a same-user process took that identity first (3 of 3
races) and switched a pool off. Orders now come only on the supervisor's own channel,
sealed with the run's key handed to the broker in the spawn. Here the same race is run
against a real pipeline: the forged switch on the workers socket and forged orders on the
orders socket itself are refused, counted once each, logged once per reason, and the pool
stays active; the supervisor's real orders (a switch off and on) still arrive.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import zmq

from tests.builders import small_source
from tests.conftest import REPO, Pipeline, only_pools, poll_for, write_config
from trapflow.wire import control_msgs, messages

pytestmark = pytest.mark.slow  # starts whole pipelines

SWITCH_OFF = messages.PoolSwitch(pool="fast", active=False)


def _node(status: dict[str, Any], name: str) -> dict[str, Any]:
    return next(n for n in status["nodes"] if n["name"] == name)


def _broker_counters(p: Pipeline) -> dict[str, int]:
    st = p.status()
    return dict(_node(st, "broker")["counters"]) if st else {}


def _pool_active(p: Pipeline) -> bool | None:
    st = p.status()
    pools = (st or {}).get("stats", {}).get("pools", {})
    return pools["fast"]["active"] if "fast" in pools else None


def _pool_cli(run_dir: Path, flag: str) -> None:
    out = subprocess.run([sys.executable, "-m", "trapflow", "pool", "fast", flag,
                          "--run-dir", str(run_dir)], capture_output=True, text=True,
                         timeout=30, cwd=REPO)
    assert out.returncode == 0, out.stderr


@pytest.mark.timeout(150)
def test_a_same_user_process_cannot_switch_a_pool_as_the_supervisor(
        spawn, run_dir: Path, zctx) -> None:
    cfg = write_config(run_dir.parent / "sup.yaml", {
        "source": small_source(15.0),
        "pools": only_pools({"fast": {"plugin": "noop", "policy": "ordered:64"}})})
    p: Pipeline = spawn(["--config", str(cfg)], run_dir)
    st = p.wait_active()
    poll_for(lambda: len(p.results()) > 5, 30, what="first results")
    os.kill(_node(st, "broker")["pid"], signal.SIGKILL)
    # The race of the issue: connect at once, with a fast reconnect, the switch queued, so
    # the forger is in before the supervisor's own socket reconnects to the new broker.
    forger = zctx.socket(zmq.DEALER)
    forger.setsockopt(zmq.IDENTITY, b"supervisor")
    forger.setsockopt(zmq.RECONNECT_IVL, 5)
    forger.connect(f"ipc://{run_dir.resolve() / 'workers.sock'}")
    forger.send_multipart([messages.encode(SWITCH_OFF)])
    orders = zctx.socket(zmq.PUSH)  # the orders socket itself: reachable, but not sealed
    orders.setsockopt(zmq.RECONNECT_IVL, 5)
    orders.connect(f"ipc://{run_dir.resolve() / 'orders.sock'}")
    orders.send_multipart([messages.encode(SWITCH_OFF)])  # unsealed, as on the old socket
    orders.send_multipart(control_msgs.seal_order(os.urandom(32), SWITCH_OFF))  # a guess
    try:
        counted = poll_for(lambda: (c := _broker_counters(p)).get("refused_forged_switch")
                           and c.get("refused_forged_order") == 2 and c, 40,
                           what="the forged switch and both forged orders counted")
        assert counted["refused_forged_switch"] == 1, counted
        # The pool never went inactive: results go on, nothing dropped for it.
        n = len(p.results())
        poll_for(lambda: len(p.results()) > n + 10, 30, what="results after the forgeries")
        assert _pool_active(p) is True
    finally:
        forger.close(linger=0)
        orders.close(linger=0)
    # The supervisor's own orders still reach the broker on its channel.
    _pool_cli(run_dir, "--deactivate")
    poll_for(lambda: _pool_active(p) is False, 20, what="the owner's switch off applied")
    _pool_cli(run_dir, "--activate")
    poll_for(lambda: _pool_active(p) is True, 20, what="the owner's switch on applied")
    time.sleep(1.0)  # a last stats beat: nothing more refused than the forgeries
    after = _broker_counters(p)
    assert (after["refused_forged_switch"], after["refused_forged_order"]) == (1, 2), after
    code, _, err = p.stop(signal.SIGINT)
    assert code == 0, err
    log_text = (run_dir / "trapflow.log").read_text()
    assert log_text.count("refused a pool switch for 'fast' from 'supervisor'") == 1
    assert log_text.count("refused a message on the supervisor's channel") == 1  # rate-limited
