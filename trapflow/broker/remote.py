"""The broker's side of workers on other hosts: the second ROUTER at network.remote.bind
(CURVE and ZAP when keys are configured) and its handshake monitor, and the JPEG pairs
remote pools get. Who joined is trapflow.broker.remote_state's table; the decisions BrokerState's.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import msgspec
import zmq

from trapflow.broker.remote_state import RemoteWorkers
from trapflow.broker.state import BrokerState
from trapflow.config.schema import Config
from trapflow.errors import ProtocolError
from trapflow.runtime.node import NodeSpec
from trapflow.runtime.ratelog import RateLimitedLog, wire
from trapflow.wire import jpeg, messages
from trapflow.wire.transport import (
    Poller,
    SocketSpec,
    open_monitor,
    open_socket,
    read_monitor,
    server_keys,
    start_authenticator,
    zmq_readable,
)

log = logging.getLogger(__name__)


class RemoteSide:
    """A base of trapflow.broker.node.BrokerNode: the remote workers' socket, read and answered.
    What it uses of the broker is declared here; the broker defines it."""

    cfg: Config
    spec: NodeSpec
    ctx: zmq.Context[zmq.Socket[bytes]]
    poller: Poller
    state: BrokerState
    ratelog: RateLimitedLog
    malformed: int
    unroutable: int
    _jpeg: dict[int, list[Any]]

    def _apply(self, actions: list[Any]) -> None:
        raise NotImplementedError  # BrokerNode's: actions to sends

    def _refuse(self, reason: str, msg: str, *args: object) -> None:
        raise NotImplementedError  # BrokerNode's: counted by reason, logged rate-limited

    def _goodbye(self, ident: bytes, reason: str) -> None:
        raise NotImplementedError  # BrokerNode's: a worker that left on purpose

    def _on_worker_msg(self, ident: bytes, msg: Any, frames: list[Any]) -> None:
        raise NotImplementedError  # BrokerNode's: a worker's message, local or remote

    def _payload(self, seq: int, copy: bool) -> list[Any]:
        raise NotImplementedError  # BrokerNode's: a pair's frames

    def _open_remote(self) -> None:
        """The ROUTER remote workers reach (network.remote.bind), with CURVE and ZAP when
        keys are configured, and a monitor that counts the handshakes it refused."""
        rc = self.cfg.network.remote
        self.remotes = RemoteWorkers()
        self.remote_router: zmq.Socket[bytes] | None = None
        self.monitor: zmq.Socket[bytes] | None = None
        self.auth: Any = None
        if not rc.bind:
            return
        curve = None
        if rc.curve:
            curve = server_keys(Path(rc.server_key))
            self.auth = start_authenticator(self.ctx, Path(rc.authorized_keys))
        self.remote_router = open_socket(self.ctx, SocketSpec(
            zmq.ROUTER, rc.bind, bind=True, router_mandatory=True, curve=curve))
        self.monitor = open_monitor(self.remote_router)
        self.poller.register(self.remote_router)
        self.poller.register(self.monitor)
        log.info("remote workers: %s (%s)", rc.bind,
                 "CURVE, authorised keys in " + rc.authorized_keys if rc.curve else "loopback, "
                 "no keys")

    def _evict_silent_hosts(self, now: float) -> None:
        """Workers whose host's supervisor went silent are gone with it: their pairs lost."""
        liveness = self.cfg.supervisor.liveness_s
        for ident in self.remotes.silent(now, liveness, self.state.worker_pools()):
            self._apply(self.state.worker_gone(
                ident, f"its host's supervisor silent for more than {liveness:g} s", now))

    def _on_handshakes(self) -> None:
        assert self.monitor is not None
        self.poller.touch(self.monitor)
        for reason in read_monitor(self.monitor):
            self._refuse(reason, "refused a remote worker's connection (%s): only clients "
                         "whose public key is in network.remote.authorized_keys may connect",
                         reason)

    def _drain_remote(self) -> None:
        """Remote workers: JoinRequest and Hello first, then the local workers' messages."""
        sock = self.remote_router
        assert sock is not None
        self.poller.touch(sock)
        for _ in range(256):
            if not zmq_readable(sock):
                return
            frames = sock.recv_multipart(copy=False)
            ident = frames[0].bytes
            try:
                if len(frames) < 2:
                    raise ProtocolError(
                        f"remote worker message: expected 2 or 3 frames, got {len(frames)}")
                msg = messages.decode_worker_msg(frames[1])
                if isinstance(msg, (messages.JoinRequest, messages.Hello)):
                    welcome, why = self._welcome(ident, msg)
                    if why:
                        self._refuse(why, "refused remote %s '%s': %s", type(msg).__name__,
                                     wire(ident.decode("utf-8", "replace")), welcome.error)
                    elif isinstance(msg, messages.Hello) and not self.remotes.joined(
                            ident, msg.host, msg.pool, msg.owner.encode(), time.monotonic()):
                        continue  # the hello of every heartbeat: known, nothing to answer
                    sock.send_multipart([ident, messages.encode(welcome)])
                elif isinstance(msg, messages.HostAlive):
                    self.remotes.owner_seen(ident, time.monotonic())
                elif isinstance(msg, messages.Gone):
                    target = msg.worker.encode()
                    if not self.remotes.may_report(ident, target):
                        self._refuse("forged_gone", "refused a gone message for worker '%s' "
                                     "from remote '%s': only that worker or its own "
                                     "supervisor may send it", wire(msg.worker),
                                     wire(ident.decode("utf-8", "replace")))
                        continue
                    self._goodbye(target, msg.reason)
                    self._apply(self.state.worker_gone(
                        target, msg.reason, time.monotonic(),
                        requeue=msg.reason.startswith(messages.GONE_RECYCLED)))
                elif isinstance(msg, messages.LadderLevel):
                    self._refuse("forged_level", "refused a ladder level from remote '%s': "
                                 "only the supervisor may send it",
                                 wire(ident.decode("utf-8", "replace")))
                elif isinstance(msg, messages.Stopping):
                    self._refuse("forged_stopping", "refused a stopping notice from remote "
                                 "'%s': only the supervisor may send it",
                                 wire(ident.decode("utf-8", "replace")))
                elif self.remotes.pool_of(ident) != msg.pool:
                    self._refuse("remote_not_joined", "refused a message from remote '%s' "
                                 "for pool '%s': expected a hello for that pool first",
                                 wire(ident.decode("utf-8", "replace")), wire(msg.pool))
                else:
                    self._on_worker_msg(ident, msg, frames)
            except ProtocolError as exc:
                self.malformed += 1
                self.ratelog.warning("remote", "dropped malformed remote message: %s", exc)
            except zmq.ZMQError as exc:  # EHOSTUNREACH: it left before its answer
                self.unroutable += 1
                self.ratelog.warning("route", "cannot answer remote %r: %s", ident, exc)

    def _welcome(self, ident: bytes, msg: messages.JoinRequest | messages.Hello
                 ) -> tuple[messages.Welcome, str]:
        """The pool's configuration for a remote worker, or the reason it may not join."""
        pcfg = self.cfg.pools.get(msg.pool)
        remote = sorted(n for n, p in self.cfg.pools.items() if p.remote)
        error, why = "", ""
        if pcfg is None or not pcfg.remote:
            why = "remote_unknown_pool"
            error = (f"pool {msg.pool!r} takes no remote workers: expected one of "
                     f"{remote or 'none'} (pools with remote: true in the pipeline's config)")
        elif isinstance(msg, messages.Hello) and (
                msg.worker.encode() != ident or "@" not in msg.worker):
            why = "remote_bad_identity"
            error = (f"expected a worker identity POOL@HOST:INDEX:PID equal to the socket's, "
                     f"got {msg.worker!r} on a socket named {ident!r}")
        if error or pcfg is None:
            return messages.Welcome(pool=msg.pool, error=error), why
        rig = self.spec.the_rig()
        return messages.Welcome(
            pool=msg.pool, plugin=self.cfg.plugin_of(msg.pool),
            pool_config=msgspec.to_builtins(pcfg), rig=msgspec.to_builtins(rig),
            heartbeat_interval_s=self.cfg.supervisor.heartbeat_interval_s), ""

    def _remote_payload(self, seq: int) -> list[Any]:
        """[header, left, right] as JPEG for a remote pool: a raw pair (the default on one
        host) is encoded once, whichever remote pools take it; a JPEG pair goes as it came."""
        cached = self._jpeg.get(seq)
        if cached is not None:
            return cached
        frames = self._payload(seq, copy=True)
        header = messages.decode_pair_header(frame_bytes(frames[0]))
        if header.encoding != "raw":
            return frames
        header, left, right = jpeg.to_jpeg_pair(header, frame_bytes(frames[1]),
                                                frame_bytes(frames[2]),
                                                self.cfg.source.jpeg_quality)
        out = [messages.encode(header), left, right]
        self._jpeg[seq] = out
        return out


def frame_bytes(frame: Any) -> bytes:
    """A frame's bytes, whether zmq gave a Frame (copy=False) or bytes."""
    return frame.bytes if isinstance(frame, zmq.Frame) else bytes(frame)
