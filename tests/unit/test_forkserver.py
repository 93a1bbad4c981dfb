"""Nodes forked from the preloaded server: the parent a node checks, the server's signals,
and its stop (trapflow.runtime.forkserver). Real processes, each waited for."""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import sys
import time
from multiprocessing import forkserver as mp_forkserver

import psutil
import pytest

from trapflow.runtime import forkserver


def _report(q: mp.Queue) -> None:  # type: ignore[type-arg]
    """What a node forked from the server sees: its parent, the parent it expects, whether
    the heavy modules were there before it imported anything, and its SIGTERM handler."""
    warm = all(m in sys.modules for m in ("numpy", "cv2", "zmq", "trapflow.config.schema"))
    q.put((os.getppid(), forkserver.expected_parent(-1), warm,
           signal.getsignal(signal.SIGTERM) == signal.SIG_IGN))


@pytest.mark.timeout(60)
def test_a_node_starts_warm_under_a_server_that_ignores_sigterm_and_stops() -> None:
    ctx = forkserver.node_context()
    q = ctx.Queue()
    p = ctx.Process(target=_report, args=(q,))
    try:
        p.start()
        parent, expected, warm, term_ignored = q.get(timeout=30)
        p.join(10)
        assert p.exitcode == 0
        server = psutil.Process(parent)
        assert parent == expected != -1 and parent != os.getpid()  # the server, not us
        assert server.ppid() == os.getpid()
        assert warm, "the server did not preload what every node imports"
        # Inherited from the server; node_main puts SIGTERM back before the node runs.
        assert term_ignored
        server.send_signal(signal.SIGTERM)  # a stop of the whole group: the server stays
        time.sleep(0.3)
        assert server.is_running() and server.status() != psutil.STATUS_ZOMBIE
    finally:
        forkserver.stop()
    assert not psutil.pid_exists(parent) or psutil.Process(parent).status() == psutil.STATUS_ZOMBIE
    assert getattr(mp_forkserver._forkserver, "_forkserver_pid", None) is None


def test_a_spawned_node_expects_the_supervisor_as_its_parent() -> None:
    """Without the server's preload module (spawn), the supervisor's pid is the parent."""
    if forkserver.PRELOAD in sys.modules:
        pytest.skip("this process imported the preload module")
    assert forkserver.expected_parent(1234) == 1234
