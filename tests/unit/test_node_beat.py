"""A node's heartbeats over a real PUSH/PULL: the beat a worker sends as it takes a pair.

Regression (issue 17, the transport bench): a worker sent one heartbeat for every pair it
took (a Heartbeat built, encoded and sent over zmq, and decoded by the supervisor): about
60 us of a worker's CPU a pair, a third of it on the raw ring path, and one message per
pair and worker into the supervisor. It now sends one at once only when its last one is
older than `fresh_s`, so the supervisor still times a pair from (at most fresh_s before)
the moment it was taken; a changed state or a due beat is never held back.
"""

from __future__ import annotations

import time
from pathlib import Path

import zmq

from tests.conftest import poll_for
from trapflow.config.schema import Config
from trapflow.runtime.node import ACTIVE, Node, NodeSpec
from trapflow.wire import messages
from trapflow.wire.endpoints import Endpoints
from trapflow.wire.transport import SocketSpec, new_context, open_socket


def _take(pull: zmq.Socket[bytes], got: list[messages.Heartbeat]) -> int:
    while pull.poll(0, zmq.POLLIN):
        got.append(messages.decode_heartbeat(pull.recv()))
    return len(got)


def _expect(pull: zmq.Socket[bytes], got: list[messages.Heartbeat], n: int) -> None:
    poll_for(lambda: _take(pull, got) >= n, 5, interval=0.01, what=f"{n} heartbeats")
    time.sleep(0.1)  # nothing more on its way
    assert _take(pull, got) == n, [(h.state, h.node) for h in got]


def test_taking_pairs_sends_one_heartbeat_per_fresh_interval_not_one_per_pair(
        run_dir: Path) -> None:
    run_dir.mkdir()
    cfg = Config()
    ctx = new_context()
    pull = open_socket(ctx, SocketSpec(zmq.PULL, Endpoints.for_run(cfg.network,
                                                                   run_dir).heartbeat,
                                       bind=True))
    node = Node(NodeSpec("worker", "worker:t:0", cfg, run_dir))
    got: list[messages.Heartbeat] = []
    try:
        node.beat()  # the first one is due
        _expect(pull, got, 1)
        for _ in range(500):  # a burst of pairs taken: the last beat is fresh
            node.beat(due=True, fresh_s=60.0)
        _expect(pull, got, 1)
        time.sleep(0.06)  # older than fresh_s now: the next pair taken is told at once
        node.beat(due=True, fresh_s=0.05)
        _expect(pull, got, 2)
        node.set_state(ACTIVE)  # a changed state is due whatever fresh_s says
        node.beat(due=True, fresh_s=60.0)
        _expect(pull, got, 3)
        assert got[-1].state == str(ACTIVE)
        node.beat(due=True)  # without fresh_s, due sends at once (capture's first pair)
        _expect(pull, got, 4)
    finally:
        node.close()
        ctx.destroy(linger=0)
