"""Node processes forked from a server that has already imported what every node needs.

A spawned node is a fresh interpreter: it imported numpy, OpenCV, pyzmq, msgspec and
trapflow's config on its own, about 0.4 s of CPU each, 2.6 s for the 7 nodes of a default
run (tripled on a loaded two-core machine), again at every restart; on a Pi that is boot
time and battery. multiprocessing's fork server imports them once (`forkserver_preload`)
and forks each node from that state: the 7 nodes then take 0.4 s of CPU together. A node
is still a process of its own with nothing of the supervisor's state (the server was
started with a clean interpreter, before any socket or ring existed), so it is as isolated
as a spawned one; it just starts warm.

How a node's life stays tied to the supervisor's (trapflow.runtime.node): the fork server
leaves when the supervisor does (its pipe to it closes, even on a kill -9: every node
closes its own copy, `detach`), and every node asks Linux to kill it when its parent, the
server, dies. The server ignores SIGTERM, so a
SIGTERM to the whole process group (systemd's stop) reaches the supervisor and the nodes
and they stop in order, rather than the server's death killing every node at once; it
ignores SIGINT as multiprocessing makes it. The supervisor stops the server when its run
ends (`stop`), so nothing of a run outlives it.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import sys
from multiprocessing import context, forkserver
from pathlib import Path

from trapflow.wire.endpoints import MAX_IPC_PATH

PRELOAD = "trapflow.runtime.forkserver_preload"
LISTENER_NAME = len("/listener-12345678")  # the server's socket file in its folder


def node_context(run_dir: Path | None = None) -> context.ForkServerContext:
    """The multiprocessing context nodes are started in (its server preloads PRELOAD).

    The server listens on a socket file; multiprocessing puts it in a `pymp-*` folder of
    the system's temporary directory, which a kill -9 of the supervisor would leave behind.
    Given the run directory (and the name fits a socket path there), it goes beside the
    run's other sockets instead, which an orderly end removes and the next start in the
    directory replaces (trapflow.supervisor.setup.clear_run_dir)."""
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload([PRELOAD])
    if run_dir is not None and len(str(run_dir.resolve())) + LISTENER_NAME <= MAX_IPC_PATH:
        # multiprocessing.util.get_temp_dir reads this before it makes a folder of its own
        mp.current_process()._config["tempdir"] = str(run_dir.resolve())  # type: ignore[attr-defined]
    return ctx


def expected_parent(supervisor_pid: int) -> int:
    """The pid a node's parent has while the supervisor lives: the fork server's in a node
    forked from it, else (a spawned node) the supervisor's."""
    preload = sys.modules.get(PRELOAD)
    server = getattr(preload, "SERVER_PID", None)
    return server if server is not None and server != os.getpid() else supervisor_pid


def detach() -> None:
    """In a node forked from the server: close its copy of the server's "alive" pipe.
    multiprocessing hands it to every child so that the server lives while any of them
    does; a node holding it kept the server up after a kill -9 of the supervisor, and the
    server, alive, kept every node up (their death signal comes with the server's end)."""
    server = getattr(forkserver, "_forkserver", None)
    fd = getattr(server, "_forkserver_alive_fd", None)
    if fd is not None and expected_parent(-1) != -1:
        try:
            os.close(fd)
        except OSError:
            pass
        server._forkserver_alive_fd = None  # type: ignore[union-attr]


def stop() -> None:
    """Stop this process's fork server now, if it runs (it leaves with this process anyway;
    stopped here, it is gone before the run is called over)."""
    server = getattr(forkserver, "_forkserver", None)
    halt = getattr(server, "_stop", None)  # public in no release; present since 3.8
    if halt is not None:
        halt()
