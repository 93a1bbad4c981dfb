"""The broker's side of workers on other hosts: the second ROUTER at network.remote.bind
(CURVE and ZAP when keys are configured) and its handshake monitor, and the JPEG pairs
remote pools get. Who joined is trapflow.broker.remote_state's table; who may say what,
trapflow.broker.trust's rules; the decisions BrokerState's.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import msgspec
import zmq

from trapflow.broker import trust
from trapflow.broker.remote_state import MAX_REMOTE_WORKERS, RemoteWorkers
from trapflow.broker.state import Action, BrokerState
from trapflow.calibration.camera import StereoRig
from trapflow.config.schema import Config
from trapflow.errors import ProtocolError
from trapflow.runtime.node import release_memory
from trapflow.runtime.ratelog import RateLimitedLog, wire
from trapflow.wire import jpeg, messages
from trapflow.wire.curve import open_monitor, read_monitor, server_keys, start_authenticator
from trapflow.wire.links import Poller
from trapflow.wire.transport import SocketSpec, open_socket, zmq_readable

log = logging.getLogger(__name__)


class RefuseFn(Protocol):
    """Count a refusal by reason and log its line, rate-limited."""

    def __call__(self, reason: str, msg: str, *args: object) -> None: ...


@dataclass(frozen=True)
class BrokerHooks:
    """What the remote side asks of the broker that owns it."""

    apply: Callable[[list[Action]], None]  # actions to sends
    refuse: RefuseFn
    goodbye: Callable[[bytes, str], None]  # a worker that left on purpose
    on_worker_msg: Callable[[bytes, trust.LocalMsg, list[Any]], None]  # as a local one's
    payload: Callable[[int, bool], list[Any]]  # a pair's frames (seq, copy)


class RemoteWorkersSide:
    """The remote workers' socket, read and answered, and who joined (roster); owned by
    trapflow.broker.node.BrokerNode."""

    def __init__(self, cfg: Config, rig: Callable[[], StereoRig],
                 ctx: zmq.Context[zmq.Socket[bytes]], poller: Poller, state: BrokerState,
                 ratelog: RateLimitedLog, hooks: BrokerHooks) -> None:
        self.cfg = cfg
        self._rig = rig
        self._poller = poller
        self._state = state
        self._ratelog = ratelog
        self._hooks = hooks
        self.roster = RemoteWorkers()
        self.malformed = 0
        self.unroutable = 0
        # Remote pools get JPEG: a raw pair is encoded once, on demand, and kept until freed.
        self._jpeg: dict[int, list[Any]] = {}
        self.router: zmq.Socket[bytes] | None = None
        self.monitor: zmq.Socket[bytes] | None = None
        self.auth: Any = None
        self._open(ctx)

    def _open(self, ctx: zmq.Context[zmq.Socket[bytes]]) -> None:
        """The ROUTER remote workers reach (network.remote.bind), with CURVE and ZAP when
        keys are configured, and a monitor that counts the handshakes it refused."""
        rc = self.cfg.network.remote
        if not rc.bind:
            return
        curve = None
        if rc.curve:
            curve = server_keys(Path(rc.server_key))
            self.auth = start_authenticator(ctx, Path(rc.authorized_keys))
        self.router = open_socket(ctx, SocketSpec(
            zmq.ROUTER, rc.bind, bind=True, router_mandatory=True, curve=curve))
        self.monitor = open_monitor(self.router)
        self._poller.register(self.router)
        self._poller.register(self.monitor)
        if rc.curve:
            log.info("remote workers: %s (CURVE, authorised keys in %s)", rc.bind,
                     rc.authorized_keys)
        else:
            # The one socket of the pipeline another local user can reach (issue 26 item 3).
            log.warning("remote workers: %s has no CURVE keys: every user of this host may "
                        "join its pools; set network.remote.server_key and authorized_keys "
                        "(`trapflow keys generate DIR`)", rc.bind)

    def close(self) -> None:
        """Stop the authenticator's thread (the sockets go with the broker's context)."""
        if self.auth is not None:
            self.auth.stop()

    def is_remote(self, ident: bytes) -> bool:
        """Whether this worker joined over the remote socket (live or evicted)."""
        return ident in self.roster.known

    def serve(self, socks: list[zmq.Socket[bytes]]) -> None:
        """Read what the poll found waiting: messages, then refused handshakes."""
        if self.router is not None and self.router in socks:
            self.drain()
        if self.monitor is not None and self.monitor in socks:
            self._on_handshakes()

    def send_job(self, ident: bytes, job: bytes, seq: int) -> None:
        """Pair `seq` to a remote worker, as JPEG (zmq.ZMQError if it is unreachable)."""
        assert self.router is not None
        self._poller.touch(self.router)
        self.router.send_multipart([ident, job, *self.jpeg_payload(seq)], copy=False)

    def release(self, seq: int) -> None:
        """No pool holds `seq` any more: its JPEG goes too."""
        self._jpeg.pop(seq, None)

    def evict_silent_hosts(self, now: float) -> None:
        """Workers whose host's supervisor went silent are gone with it: their pairs lost.
        Hellos never followed by work are forgotten once silent (the table stays bounded)."""
        liveness = self.cfg.supervisor.liveness_s
        live = self._state.worker_pools()
        for ident in self.roster.silent(now, liveness, live):
            self._hooks.apply(self._state.worker_gone(
                ident, f"its host's supervisor silent for more than {liveness:g} s", now))
        if self.roster.forget_stale(now, liveness, live):
            release_memory()  # their connections' buffers, freed by libzmq, go back too

    def counters(self) -> dict[str, int]:
        """For the broker's counters: remote entries forgotten as stale."""
        return {"remote_forgotten": self.roster.forgotten} if self.roster.forgotten else {}

    def _on_handshakes(self) -> None:
        assert self.monitor is not None
        self._poller.touch(self.monitor)
        for reason in read_monitor(self.monitor):
            self._hooks.refuse(reason, "refused a remote worker's connection (%s): only "
                               "clients whose public key is in "
                               "network.remote.authorized_keys may connect", reason)

    def drain(self) -> None:
        """Remote workers: JoinRequest and Hello first, then the local workers' messages."""
        sock = self.router
        assert sock is not None
        self._poller.touch(sock)
        for _ in range(256):
            if not zmq_readable(sock):
                return
            frames = sock.recv_multipart(copy=False)
            ident = frames[0].bytes
            try:
                if len(frames) < 2:
                    raise ProtocolError(
                        f"remote worker message: expected 2 or 3 frames, got {len(frames)}")
                self._on_message(ident, messages.decode_worker_msg(frames[1]), frames)
            except ProtocolError as exc:
                self.malformed += 1
                self._ratelog.warning("remote", "dropped malformed remote message: %s", exc)
            except zmq.ZMQError as exc:  # EHOSTUNREACH: it left before its answer
                self.unroutable += 1
                self._ratelog.warning("route", "cannot answer remote %r: %s", ident, exc)

    def _on_message(self, ident: bytes, msg: messages.WorkerMsg, frames: list[Any]) -> None:
        self.roster.heard(ident, time.monotonic())
        verdict = trust.on_remote_socket(ident, msg, self.roster)
        if isinstance(verdict, trust.Refuse):
            self._hooks.refuse(verdict.reason, verdict.message, *verdict.args)
            return
        if isinstance(msg, (messages.JoinRequest, messages.Hello)):
            welcome, why = self._welcome(ident, msg)
            if why:
                self._hooks.refuse(why, "refused remote %s '%s': %s", type(msg).__name__,
                                   wire(ident.decode("utf-8", "replace")), welcome.error)
            elif isinstance(msg, messages.Hello) and not self.roster.joined(
                    ident, msg.host, msg.pool, msg.owner.encode(), time.monotonic()):
                return  # the hello of every heartbeat: known, nothing to answer
            assert self.router is not None
            self.router.send_multipart([ident, messages.encode(welcome)])
        elif isinstance(msg, messages.HostAlive):
            self.roster.owner_seen(ident, time.monotonic())
        elif isinstance(msg, messages.Gone):
            target = msg.worker.encode()
            self._hooks.goodbye(target, msg.reason)
            self._hooks.apply(self._state.worker_gone(
                target, msg.reason, time.monotonic(),
                requeue=msg.reason.startswith(messages.GONE_RECYCLED)))
        else:
            # A joined worker's Ready, Alive, Done, Failed or PoolSwitch (trust refused a
            # remote's LadderLevel and Stopping above), taken as a local worker's.
            self._hooks.on_worker_msg(ident, msg, frames)

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
        elif isinstance(msg, messages.Hello) and self.roster.full(ident):
            why = "remote_table_full"
            error = (f"the pipeline takes at most {MAX_REMOTE_WORKERS} remote workers at once; "
                     f"try again once one left (silent ones are forgotten after "
                     f"{self.cfg.supervisor.liveness_s:g} s)")
        if error or pcfg is None:
            return messages.Welcome(pool=msg.pool, error=error), why
        rig = self._rig()
        return messages.Welcome(
            pool=msg.pool, plugin=self.cfg.plugin_of(msg.pool),
            pool_config=msgspec.to_builtins(pcfg), rig=msgspec.to_builtins(rig),
            heartbeat_interval_s=self.cfg.supervisor.heartbeat_interval_s), ""

    def jpeg_payload(self, seq: int) -> list[Any]:
        """[header, left, right] as JPEG for a remote pool: a raw pair (the default on one
        host) is encoded once, whichever remote pools take it; a JPEG pair goes as it came."""
        cached = self._jpeg.get(seq)
        if cached is not None:
            return cached
        frames = self._hooks.payload(seq, True)
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
