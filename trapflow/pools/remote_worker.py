"""`trapflow worker` on another host: a small supervisor that asks the pipeline how a pool
runs, then starts, watches and restarts that many worker processes that join it.

Owns a DEALER to the broker's remote ROUTER (network.remote.bind, CURVE with --keys): the
pool request, and Gone for a worker process that died. Each worker process has its own
DEALER: Hello (answered by a Welcome), then Ready, jobs as bytes, Alive, as on one host.
"""

from __future__ import annotations

import logging
import os
import signal
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import zmq

from trapflow import registry
from trapflow.calibration.camera import StereoRig
from trapflow.config import schema as configmod
from trapflow.errors import ConfigError, ProtocolError, StartupError
from trapflow.pools.worker import WorkerNode
from trapflow.runtime import forkserver
from trapflow.runtime.lifecycle import RECYCLE_EXITS
from trapflow.runtime.logchannel import LogListener
from trapflow.runtime.node import JoinSpec, NodeSpec, node_main
from trapflow.wire import identity, messages
from trapflow.wire.curve import client_keys
from trapflow.wire.endpoints import log_endpoint
from trapflow.wire.transport import SocketSpec, new_context, open_socket

log = logging.getLogger(__name__)

JOIN_TIMEOUT_S = 10.0  # how long a Welcome may take (connection, handshake, broker busy)
ASK_RETRY_S = 2.0  # a request is sent again this often while no Welcome came
WATCH_INTERVAL_S = 0.2  # how often the supervisor looks at its worker processes
RESTART_BACKOFF_S = 0.5  # first restart delay, doubled per quick death, up to the max
RESTART_BACKOFF_MAX_S = 10.0
STABLE_S = 10.0  # a process that lived this long resets the back-off
STOP_TIMEOUT_S = 3.0  # stop ladder: SIGTERM, wait this long, SIGKILL


def dealer_spec(join: JoinSpec, identity: str) -> SocketSpec:
    """The DEALER a process of this host opens to the pipeline."""
    curve = client_keys(Path(join.keys)) if join.keys else None
    return SocketSpec(zmq.DEALER, join.endpoint, identity=identity.encode(), curve=curve)


def ask(sock: zmq.Socket[bytes], msg: messages.Msg, endpoint: str,
        timeout_s: float = JOIN_TIMEOUT_S) -> messages.Welcome:
    """Send msg (again every ASK_RETRY_S) until the pipeline's Welcome answers it."""
    deadline = time.monotonic() + timeout_s
    next_send = 0.0
    while (now := time.monotonic()) < deadline:
        if now >= next_send:
            next_send = now + ASK_RETRY_S
            try:
                sock.send(messages.encode(msg), zmq.NOBLOCK)
            except zmq.Again:
                pass  # not connected yet and the queue is full: the next try
        if not sock.poll(100, zmq.POLLIN):
            continue
        frames = sock.recv_multipart()
        if len(frames) != 1:
            continue  # a job for an identity that left: not ours to answer
        welcome = messages.decode_welcome(frames[0])
        if welcome.error:
            raise StartupError(f"the pipeline at {endpoint} refused pool {welcome.pool!r}: "
                               f"{welcome.error}")
        return welcome
    raise StartupError(
        f"no answer from the pipeline at {endpoint} within {timeout_s:g} s: expected a welcome; "
        "is a pipeline running there with network.remote.bind, and is this host's public key "
        "(client.key) in its network.remote.authorized_keys?")


def config_from(welcome: messages.Welcome, pool: str) -> tuple[configmod.Config, StereoRig]:
    """The pipeline's pool configuration and rig, validated as if read from its YAML."""
    data = {**welcome.pool_config, "count": 1, "remote": True}
    try:
        cfg = configmod.from_data({
            "pools": {pool: data},
            "supervisor": {"heartbeat_interval_s": welcome.heartbeat_interval_s},
        }, f"welcome for pool {pool!r}")
        rig = msgspec.convert(welcome.rig, StereoRig)
    except (msgspec.ValidationError, ValueError) as exc:
        raise ProtocolError(f"welcome for pool {pool!r}: rig: {exc}") from None
    except ConfigError as exc:
        raise ProtocolError(str(exc)) from None
    return cfg, rig


class RemoteWorkerNode(WorkerNode):
    """A worker process of a pool on another host: WorkerNode over the remote socket."""

    @property
    def join(self) -> JoinSpec:
        join = self.spec.join
        assert join is not None, "a remote worker is spawned with its JoinSpec"
        return join

    def _identity(self) -> str:
        return identity.remote_identity(self.pool, self.join.host, self.spec.index, os.getpid())

    def _hello(self) -> messages.Hello:
        return messages.Hello(worker=self.ident, pool=self.pool, host=self.join.host,
                              owner=self.join.owner)

    def _open_dealer(self) -> zmq.Socket[bytes]:
        sock = open_socket(self.ctx, dealer_spec(self.join, self.ident))
        ask(sock, self._hello(), self.join.endpoint)
        return sock

    def beat(self, due: bool = False, fresh_s: float = 0.0) -> None:
        """No supervisor on this host reads node heartbeats: the broker hears Alive."""

    def _send(self, msgs: list[Any]) -> None:
        # Hello with every Alive: a broker restarted since (kill -9) learns who this is.
        if msgs and isinstance(msgs[0], messages.Alive):
            super()._send([self._hello()])
        super()._send(msgs)

    def _recv(self, timeout_ms: int) -> list[Any] | None:
        frames = super()._recv(timeout_ms)
        if frames is None or len(frames) != 1:
            return frames
        try:  # the broker's answer to a Hello
            welcome = messages.decode_welcome(frames[0])
        except ProtocolError as exc:
            self.ratelog.warning("welcome", "%s: dropped a malformed message: %s",
                                 self.ident, exc)
            return None
        if welcome.error:
            log.error("%s: the pipeline refused this worker: %s", self.ident, welcome.error)
            self.stopping = True
        return None


@dataclass
class _Proc:
    index: int
    proc: Any = None  # multiprocessing.Process
    started: float = 0.0
    restart_at: float = 0.0
    quick_deaths: int = 0
    restarts: int = 0


class RemotePool:
    """The small supervisor of `trapflow worker`: count processes, restarted when they die."""

    def __init__(self, join: JoinSpec, pool: str, count: int, run_dir: Path,
                 announce: Callable[[str], None] = print,
                 join_timeout_s: float = JOIN_TIMEOUT_S) -> None:
        self.join, self.pool, self.count, self.run_dir = join, pool, count, run_dir
        self.join_timeout_s = join_timeout_s
        self.announce = announce
        self.stopping = False
        self.mp = forkserver.node_context(run_dir)
        self.procs = [_Proc(i) for i in range(count)]

    def run(self) -> int:
        """Join, supervise until SIGINT or SIGTERM, stop; return the exit status."""
        ctx = new_context()
        # The worker processes' records, over log.sock in the run directory (no semaphore).
        listener = LogListener(ctx, log_endpoint(self.run_dir), logging.getLogger().handlers)
        listener.start()
        try:
            self.sock = open_socket(ctx, dealer_spec(self.join, self.join.owner))
            welcome = ask(self.sock, messages.JoinRequest(pool=self.pool, host=self.join.host),
                          self.join.endpoint, self.join_timeout_s)
            cfg, rig = config_from(welcome, self.pool)
            registry.resolve(cfg.plugin_of(self.pool))  # fail here, not in every process
            self.announce(f"joined pool {self.pool!r} at {self.join.endpoint} as "
                          f"{self.join.host}: {self.count} worker(s) of {welcome.plugin!r}")
            self._install_signals()
            self._supervise(cfg, rig)
        finally:
            self._stop_all()
            forkserver.stop()  # the worker processes' server: nothing of this run outlives it
            listener.stop()  # its thread's socket is in the context: stop it first
            ctx.destroy(linger=0)
        return 0

    def _install_signals(self) -> None:
        def _stop(_signo: int, _frame: Any) -> None:
            self.stopping = True

        signal.signal(signal.SIGINT, _stop)
        signal.signal(signal.SIGTERM, _stop)

    def _supervise(self, cfg: configmod.Config, rig: StereoRig) -> None:
        next_alive = 0.0
        while not self.stopping:
            now = time.monotonic()
            if now >= next_alive:  # this host is up, even while every worker computes
                next_alive = now + cfg.supervisor.heartbeat_interval_s
                self._send(messages.HostAlive(host=self.join.host))
            for p in self.procs:
                if p.proc is None:
                    if now >= p.restart_at:
                        self._spawn(p, cfg, rig)
                elif not p.proc.is_alive():
                    self._died(p, now)
            self._drain()
            time.sleep(WATCH_INTERVAL_S)

    def _spawn(self, p: _Proc, cfg: configmod.Config, rig: StereoRig) -> None:
        spec = NodeSpec("remote_worker", f"worker:{self.pool}@{self.join.host}:{p.index}", cfg,
                        self.run_dir, pool=self.pool, index=p.index, rig=rig,
                        join=self.join)
        p.proc = self.mp.Process(target=node_main, args=(spec, os.getpid()),
                                 name=spec.name, daemon=False)
        p.proc.start()
        p.started = time.monotonic()

    def _died(self, p: _Proc, now: float) -> None:
        """Tell the broker at once (its pairs are lost, not timed out), restart later."""
        ident = identity.remote_identity(self.pool, self.join.host, p.index, p.proc.pid)
        code = p.proc.exitcode
        why = RECYCLE_EXITS.get(code, "") if code is not None else ""
        if why:  # recycled on purpose (max_rss_mb, max_jobs): replaced at once
            self._send(messages.Gone(worker=ident, reason=messages.recycled_reason(why)))
            log.info("worker %s recycled (%s); replacing it", ident, why)
            p.proc.join(0)
            p.proc, p.restart_at = None, now
            return
        reason = f"exited with status {code}" if code is not None and code >= 0 else (
            f"killed by signal {-(code or 0)}")
        self._send(messages.Gone(worker=ident, reason=reason))
        p.quick_deaths = 0 if now - p.started >= STABLE_S else p.quick_deaths + 1
        delay = min(RESTART_BACKOFF_S * 2 ** max(p.quick_deaths - 1, 0), RESTART_BACKOFF_MAX_S)
        log.warning("worker %s %s; restarting in %.1f s", ident, reason, delay)
        p.proc.join(0)
        p.proc, p.restart_at = None, now + delay
        p.restarts += 1

    def _send(self, msg: messages.Msg) -> None:
        try:
            self.sock.send(messages.encode(msg), zmq.NOBLOCK)
        except zmq.Again:
            pass  # not connected (broker restarting): the broker's own timeouts decide

    def _drain(self) -> None:
        """Late Welcomes (a request sent twice) are read and forgotten."""
        while self.sock.poll(0, zmq.POLLIN):
            self.sock.recv_multipart()

    def _stop_all(self) -> None:
        """Ask (SIGTERM: each leaves with Gone), wait, kill, join."""
        live = [p.proc for p in self.procs if p.proc is not None]
        for proc in live:
            if proc.is_alive():
                proc.terminate()
        deadline = time.monotonic() + STOP_TIMEOUT_S
        for proc in live:
            proc.join(max(deadline - time.monotonic(), 0))
            if proc.is_alive():
                proc.kill()
                proc.join(5)


def run(endpoint: str, pool: str, count: int, keys: Path | None, host: str,
        run_dir: Path | None = None, join_timeout_s: float = JOIN_TIMEOUT_S,
        announce: Callable[[str], None] = print) -> int:
    """`trapflow worker`: join the pipeline at endpoint with count processes of pool."""
    if not pool.isidentifier():
        raise ConfigError(f"--pool: expected a pool name (an identifier), got {pool!r}")
    owner = identity.owner_identity(host, os.getpid())
    join = JoinSpec(endpoint, str(keys.resolve()) if keys else "", host, owner)
    tmp = None
    if run_dir is None:  # only debug output (`save: true`) lands here
        tmp = tempfile.TemporaryDirectory(prefix="tf-worker-")
        run_dir = Path(tmp.name)
    run_dir.mkdir(parents=True, exist_ok=True)
    try:
        return RemotePool(join, pool, count, run_dir, announce, join_timeout_s).run()
    finally:
        if tmp is not None:
            tmp.cleanup()
