"""The process base class: title, signals, faulthandler, logging, heartbeats, lifecycle.

Every pipeline process is a Node started by the supervisor with the spawn method;
subclasses write only run(). Owns one socket: a PUSH of heartbeats to the supervisor (and
through its log handler, trapflow.runtime.logchannel, a PUSH of log records).
"""

from __future__ import annotations

import ctypes
import faulthandler
import gc
import importlib
import logging
import os
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import zmq

from trapflow.calibration.camera import StereoRig
from trapflow.config.schema import Config
from trapflow.runtime import forkserver
from trapflow.runtime.lifecycle import Lifecycle
from trapflow.runtime.logchannel import LogSender
from trapflow.wire import messages
from trapflow.wire.endpoints import Endpoints, log_endpoint
from trapflow.wire.transport import SocketSpec, new_context, open_socket

log = logging.getLogger(__name__)

# ROS 2 lifecycle states (the enum lives in the pure supervision core).
UNCONFIGURED: Final = Lifecycle.UNCONFIGURED
INACTIVE: Final = Lifecycle.INACTIVE
ACTIVE: Final = Lifecycle.ACTIVE
FINALIZED: Final = Lifecycle.FINALIZED

# Exit code of a node that ended on purpose (finite source exhausted): not a crash.
EXIT_FINISHED = 0
# Exit code of a node whose main loop raised: the supervisor restarts it.
EXIT_CRASHED = 1

# Role -> Node class; the supervisor spawns nodes by role name.
ROLES = {
    "capture": "trapflow.capture.node:CaptureNode",
    "broker": "trapflow.broker.node:BrokerNode",
    "worker": "trapflow.pools.worker:WorkerNode",
    "remote_worker": "trapflow.pools.remote_worker:RemoteWorkerNode",  # `trapflow worker`
    "normalizer": "trapflow.normalizer.node:NormalizerNode",
    "modem": "trapflow.modem.node:ModemNode",
    "events": "trapflow.events.node:EventsNode",
    "viewer": "trapflow.viewer.node:ViewerNode",
}

_PR_SET_PDEATHSIG = 1
# Set to a folder to have every node write a cProfile of its loop there on exit.
PROFILE_ENV = "TRAPFLOW_PROFILE_DIR"


@dataclass(frozen=True)
class JoinSpec:
    """How a worker process on another host reaches the pipeline (`trapflow worker`)."""

    endpoint: str  # tcp://HOST:PORT of the pipeline's network.remote.bind
    keys: str  # folder with client.key_secret and server.key; empty: no CURVE (loopback)
    host: str  # this host's name in identities and status
    owner: str  # the identity of this host's `trapflow worker` supervisor


@dataclass(frozen=True)
class NodeSpec:
    """What the supervisor tells a node it spawns (picklable, crosses the spawn boundary)."""

    role: str
    name: str  # e.g. "worker:mono:1"
    cfg: Config
    run_dir: Path
    pool: str = ""
    index: int = 0
    rig: StereoRig | None = None  # the run's rig, decided once by trapflow.sources.rig at preflight
    tag_size_m: float | None = None  # the tags the source lays, where it knows (sources.rig)
    ring: str = ""  # the shared-memory frame ring's segment name ("" without one)
    # A restarted broker frees the ring slots its predecessor held; a first one must not
    # (capture's first pairs may already hold slots on their way to it).
    restarted: bool = False
    first_seq: int = 0  # capture numbers pairs from here (past a predecessor's numbers)
    join: JoinSpec | None = None  # a remote worker's way to the pipeline
    # This start of the pipeline (the supervisor's), the same for a restarted node: state a
    # node saved under another id predates a restart of the box (its runtime changes gone).
    run_id: str = ""
    # The broker's: the key that seals the supervisor's orders (control_msgs.seal_order).
    # Crosses the spawn in the pickled spec, never on a command line or in the environment.
    order_key: bytes = field(default=b"", repr=False)
    # The viewer's: its token (trapflow.viewer.access.new_token), made by the supervisor that
    # prints it; crosses the spawn the same way, and a restarted viewer keeps it.
    viewer_token: str = field(default="", repr=False)

    def the_rig(self) -> StereoRig:
        """The run's rig; a node spawned without one (a test, a benchmark) gets the config's."""
        if self.rig is not None:
            return self.rig
        from trapflow.sources.rig import from_config  # the rig module imports sources: keep it lazy

        return from_config(self.cfg)


class Node:
    """Base of every pipeline process."""

    def __init__(self, spec: NodeSpec) -> None:
        self.spec = spec
        self.cfg = spec.cfg
        self.name = spec.name
        self.endpoints = Endpoints.for_run(spec.cfg.network, spec.run_dir)
        self.lifecycle: Lifecycle = UNCONFIGURED
        self.reason = ""
        self.stopping = False
        self.ctx = new_context()
        self._hb = open_socket(
            self.ctx, SocketSpec(zmq.PUSH, self.endpoints.heartbeat, sndhwm=10)
        )
        self._hb_interval_ns = int(spec.cfg.supervisor.heartbeat_interval_s * 1e9)
        self._next_beat = 0
        self._last_beat = 0  # when the last heartbeat left (monotonic ns)

    def set_state(self, state: Lifecycle, reason: str = "", normal: bool = False) -> None:
        """Move to a lifecycle state and tell the supervisor at once. A reason is a
        warning unless the change is `normal` (a planned end: a source exhausted)."""
        if (state, reason) != (self.lifecycle, self.reason):
            if reason and not normal:
                log.warning("%s: %s (%s)", self.name, state, reason)
            else:
                log.info("%s: %s%s", self.name, state, f" ({reason})" if reason else "")
        self.lifecycle, self.reason = state, reason
        self._next_beat = 0

    def counters(self) -> dict[str, int]:
        """Counters sent with every heartbeat; subclasses override."""
        return {}

    def beat(self, due: bool = False, fresh_s: float = 0.0) -> None:
        """Send a heartbeat if one is due, or at once with `due` (never blocks). With
        `fresh_s`, `due` sends only if the last heartbeat left more than fresh_s ago: the
        supervisor then hears of the moment at most fresh_s late, and a caller on a hot
        path (a worker taking a pair) sends a few a second instead of one per call."""
        now = time.monotonic_ns()
        if now < self._next_beat and not (due and now - self._last_beat >= fresh_s * 1e9):
            return
        self._last_beat = now
        self._next_beat = now + self._hb_interval_ns
        hb = messages.Heartbeat(
            node=self.name, pid=os.getpid(), state=self.lifecycle, reason=self.reason,
            counters=self.counters(),
        )
        try:
            self._hb.send(messages.encode(hb), zmq.NOBLOCK)
        except zmq.Again:
            pass  # supervisor busy or gone; it judges liveness, not us

    def run(self) -> int:
        """The node's loop; return an exit code when self.stopping is set."""
        raise NotImplementedError

    def close(self) -> None:
        """Send a last heartbeat (final counters for the ledger), then release sockets."""
        self._next_beat = 0
        self.beat()
        self._hb.close(linger=300)  # give that last heartbeat a moment to leave
        self.ctx.destroy(linger=0)


def release_memory() -> None:
    """Give the allocator's free pages back to the system (glibc's malloc_trim). libzmq frees
    its record of a peer's subscriptions when the peer leaves, but the pages stay with the
    process: 50,000 random subscriptions left +6.3 MB after their sender left, +1.7 MB after
    a trim (measured, issue 26 item 10). Elsewhere than glibc, nothing to do."""
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None).malloc_trim(0)
        except (OSError, AttributeError):
            pass  # musl and others: no malloc_trim


def _die_with_parent() -> None:
    """Ask Linux to SIGKILL us if the supervisor dies, so no orphan survives a kill -9."""
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
        except OSError:
            pass


def _set_title(title: str) -> None:
    try:
        import setproctitle

        setproctitle.setproctitle(title)
    except ImportError:  # optional nicety
        pass


def _report_death(spec: NodeSpec, node: Node | None, reason: str) -> None:
    """Tell the supervisor why we die, so start-up failures read as one clear line."""
    hb = messages.Heartbeat(node=spec.name, pid=os.getpid(), state=FINALIZED, reason=reason)
    if node is not None:
        node.lifecycle, node.reason = FINALIZED, reason
        node._next_beat = 0
        node.beat()
        return
    try:
        ctx = new_context()
        sock = open_socket(ctx, SocketSpec(
            zmq.PUSH, Endpoints.for_run(spec.cfg.network, spec.run_dir).heartbeat))
        sock.send(messages.encode(hb), zmq.NOBLOCK)
        sock.close(linger=500)  # give the one message a moment to leave
        ctx.term()
    except Exception:  # noqa: BLE001 - best effort on the way out
        pass


def freeze_heap() -> None:
    """Start-up is over: what exists now lives for the whole run. Frozen, the cyclic
    collector never walks it again; walking the heap of numpy, OpenCV and a model in
    every collection cost a worker about a tenth of its CPU per pair."""
    gc.collect()
    gc.freeze()


def node_main(spec: NodeSpec, parent_pid: int) -> None:
    """Entry point of every spawned node process."""
    _die_with_parent()
    forkserver.detach()  # the server leaves with the supervisor, and we with the server
    if os.getppid() != forkserver.expected_parent(parent_pid):  # it died before prctl took effect
        os._exit(EXIT_CRASHED)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # the fork server ignores it
    _set_title(f"trapflow:{spec.name}")
    faulthandler.enable()
    root = logging.getLogger()
    root.handlers[:] = [LogSender(log_endpoint(spec.run_dir), spec.name)]
    root.setLevel(spec.cfg.log_level)
    # Ctrl-C reaches the whole process group; only the supervisor acts on it, in order.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    module_name, _, cls_name = ROLES[spec.role].partition(":")
    cls = getattr(importlib.import_module(module_name), cls_name)
    node: Node | None = None
    code = EXIT_CRASHED
    try:
        node = cls(spec)

        def _term(_signo: int, _frame: Any) -> None:
            assert node is not None
            node.stopping = True

        signal.signal(signal.SIGTERM, _term)
        freeze_heap()
        profile_dir = os.environ.get(PROFILE_ENV)
        if profile_dir:  # developer aid: where does this node spend its time?
            import cProfile

            prof = cProfile.Profile()
            code = prof.runcall(node.run)
            prof.dump_stats(str(Path(profile_dir) / f"{spec.name.replace(':', '-')}.prof"))
        else:
            code = node.run()
    except Exception as exc:
        log.exception("%s crashed", spec.name)
        _report_death(spec, node, f"{type(exc).__name__}: {exc}")
        code = EXIT_CRASHED
    finally:
        if node is not None:
            node.close()
        logging.shutdown()
    sys.exit(code)
