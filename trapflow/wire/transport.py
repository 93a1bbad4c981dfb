"""The only module that opens ZeroMQ sockets: SocketSpec -> open socket, with the size cap a
bound socket takes from a peer, and the process's one context.

Sockets are opened inside the process that uses them (never inherited across a fork), from
that process's single context, with linger 0 so shutdown never hangs. Where they live is
endpoints.py; CURVE keys and the authenticator curve.py; the local links (UNIX seqpacket)
and the poller over both links.py; the tap's subscription policy tap_gate.py.
"""

from __future__ import annotations

import errno
import os
from dataclasses import dataclass

import zmq

from trapflow.errors import StartupError
from trapflow.wire import messages
from trapflow.wire.endpoints import SOCKET_MODE

# The largest message part a bound socket takes from a peer (ZMQ_MAXMSGSIZE): a bigger one
# disconnects that peer before anything is allocated. Each fits the largest legitimate
# message with room to spare (ZeroMQ's handshake passes through the same limit).
TAP_MAX_MSG_BYTES = 1024  # taps (XPUB) read only subscriptions: a topic prefix and one byte
SMALL_MAX_MSG_BYTES = 64 << 10  # heartbeats, control requests: at most MAX_HEADER_BYTES each
WORKERS_MAX_MSG_BYTES = messages.MAX_RESULT_BYTES + (64 << 10)  # a Done and its result
PAIR_MAX_MSG_BYTES = messages.MAX_SIDE * messages.MAX_SIDE * 3  # one raw image of a pair
_BOUND_MAX_MSG_BYTES: dict[int, int] = {
    int(zmq.XPUB): TAP_MAX_MSG_BYTES,
    int(zmq.PUB): TAP_MAX_MSG_BYTES,
    int(zmq.PULL): SMALL_MAX_MSG_BYTES,  # heartbeats; the broker's capture PULL sets its own
    int(zmq.REP): SMALL_MAX_MSG_BYTES,
    int(zmq.ROUTER): WORKERS_MAX_MSG_BYTES,
}


@dataclass(frozen=True)
class CurveKeys:
    """This side's CURVE key pair (Z85), and for a client the server's public key."""

    public: bytes
    secret: bytes
    server: bytes | None = None  # None: this side is the server

    def __repr__(self) -> str:  # never print a secret key into a log
        return f"CurveKeys(public={self.public!r}, server={self.server!r})"


@dataclass(frozen=True)
class SocketSpec:
    """Everything needed to open one socket."""

    kind: int  # zmq.PUSH, zmq.PULL, ...
    endpoint: str
    bind: bool = False
    sndhwm: int = 1000
    rcvhwm: int = 1000
    identity: bytes | None = None
    subscribe: tuple[bytes, ...] = ()
    router_mandatory: bool = False
    # Largest message part taken from a peer; None: a bound socket's default for its kind.
    max_msg_bytes: int | None = None
    xpub_manual: bool = False  # XPUB: the process decides which subscriptions count (TapGate)
    curve: CurveKeys | None = None  # CURVE encryption and authentication
    # More endpoints a connecting socket connects to (a SUB on two taps).
    also_connect: tuple[str, ...] = ()


def open_socket(ctx: zmq.Context[zmq.Socket[bytes]], spec: SocketSpec) -> zmq.Socket[bytes]:
    """Open, configure and bind or connect a socket; StartupError if the address is taken."""
    sock = ctx.socket(spec.kind)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.SNDHWM, spec.sndhwm)
    sock.setsockopt(zmq.RCVHWM, spec.rcvhwm)
    if spec.identity is not None:
        sock.setsockopt(zmq.IDENTITY, spec.identity)
    if spec.router_mandatory:
        sock.setsockopt(zmq.ROUTER_MANDATORY, 1)
    cap = spec.max_msg_bytes
    if cap is None and spec.bind:
        cap = _BOUND_MAX_MSG_BYTES.get(int(spec.kind))
    if cap is not None:
        sock.setsockopt(zmq.MAXMSGSIZE, cap)
    if spec.xpub_manual:
        sock.setsockopt(zmq.XPUB_MANUAL, 1)
    for topic in spec.subscribe:
        sock.setsockopt(zmq.SUBSCRIBE, topic)
    if spec.curve is not None:
        sock.setsockopt(zmq.CURVE_PUBLICKEY, spec.curve.public)
        sock.setsockopt(zmq.CURVE_SECRETKEY, spec.curve.secret)
        if spec.curve.server is None:
            sock.setsockopt(zmq.CURVE_SERVER, 1)
        else:
            sock.setsockopt(zmq.CURVE_SERVERKEY, spec.curve.server)
    try:
        if spec.bind:
            sock.bind(spec.endpoint)
            if spec.endpoint.startswith("ipc://"):
                # The socket file follows the umask; the run directory is 0700 anyway.
                os.chmod(spec.endpoint[len("ipc://"):], SOCKET_MODE)
        else:
            for endpoint in (spec.endpoint, *spec.also_connect):
                sock.connect(endpoint)
    except zmq.ZMQError as exc:
        sock.close(linger=0)
        verb = "bind" if spec.bind else "connect to"
        where = ", ".join((spec.endpoint, *spec.also_connect))
        if exc.errno == errno.EADDRINUSE:
            raise StartupError(f"cannot {verb} {where}: address already in use") from None
        raise StartupError(f"cannot {verb} {where}: {exc}") from None
    return sock


def set_subscribed(sock: zmq.Socket[bytes], topic: bytes, on: bool) -> None:
    """Subscribe a SUB socket to topic, or unsubscribe it (the publisher hears either)."""
    sock.setsockopt(zmq.SUBSCRIBE if on else zmq.UNSUBSCRIBE, topic)


def new_context() -> zmq.Context[zmq.Socket[bytes]]:
    """The one context of a process (created in the process, never inherited)."""
    return zmq.Context()




_EVENTS, _POLLIN = int(zmq.EVENTS), int(zmq.POLLIN)  # plain ints: no enum conversion


def zmq_readable(sock: zmq.Socket[bytes]) -> bool:
    """A message is waiting. Cheaper than a failed recv on a hot path, and reading
    EVENTS re-arms the socket's notification descriptor."""
    events = sock.getsockopt(_EVENTS)
    return isinstance(events, int) and bool(events & _POLLIN)
