"""The only module that creates sockets: an endpoint table, SocketSpec -> open socket,
and the local links that carry shared-memory descriptors on one host, with one poller
over both. It also loads CURVE keys, and starts the ZAP authenticator and the handshake
monitor of a socket that remote workers reach.

Sockets are opened inside the process that uses them (never inherited across a
fork), from that process's single context, with linger 0 so shutdown never hangs.
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import socket
import stat
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zmq

from trapflow.config.schema import NetworkConfig
from trapflow.errors import ProtocolError, StartupError, TrapflowError
from trapflow.wire import frame_msgs, messages

# Linux limits a UNIX socket path to 107 bytes.
MAX_IPC_PATH = 107

# The pipeline's sockets, ipc files in its run directory (0700, sockets 0600): only the
# directory's owner reaches them, in every mode (network.transport tcp once put five on
# loopback ports that every local user could reach: issue 26 item 3). The only TCP socket
# is network.remote.bind (CURVE keys). The supervisor, broker and normalizer bind these.
_ENDPOINTS = {
    "capture": "capture.sock",  # capture PUSH -> broker PULL
    "workers": "workers.sock",  # broker ROUTER <-> worker DEALERs
    "tap": "tap.sock",  # broker PUB: frames and stats
    "results_tap": "results-tap.sock",  # normalizer PUB: JSON results
    "heartbeat": "heartbeat.sock",  # nodes PUSH -> supervisor PULL
    "control": "control.sock",  # supervisor REP: status, stop
    "log": "log.sock",  # nodes PUSH -> supervisor PULL: log records (control_msgs.LogEntry)
    # supervisor PUSH -> broker PULL: pool switches, the ladder's level, workers gone, the
    # stop (control_msgs.seal_order: each sealed with the run's key, handed in the spawn)
    "orders": "orders.sock",
}
# Modes that hold whatever the umask: the run directory is its owner's alone; sockets and
# links in it are read-write for the owner only; results and logs may be read by its group.
RUN_DIR_MODE = 0o700
SOCKET_MODE = 0o600
FILE_MODE = 0o640
# Local links (always files in the run directory): descriptors of pairs in the ring, results.
_LINKS = {
    "capture_link": "capture.link",  # capture -> broker
    "workers_link": "workers.link",  # broker <-> local workers
    "results_link": "results.link",  # broker -> normalizer, results in batches
}


def check_ports_free(net: NetworkConfig) -> None:
    """StartupError naming network.remote.bind's port when another process holds it.

    The supervisor asks before it creates anything big (the ring), so a second pipeline on
    the same port ends in one line with nothing left behind. Without a remote bind, nothing
    to check (every other socket is an ipc file in the run directory).
    """
    if not net.remote.bind:
        return
    host, _, port = net.remote.bind.partition("://")[2].rpartition(":")
    host = host.strip("[]")
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("" if host in ("*", "0.0.0.0") else host, int(port)))
        except OSError as exc:
            why = (exc.strerror or str(exc)).lower()
            raise StartupError(
                f"cannot start: cannot bind {net.remote.bind} (network.remote.bind): {why}; "
                f"another pipeline or program holds it: stop it, or choose another port"
            ) from None


def _ipc_url(run_dir: Path, fname: str) -> str:
    path = str(run_dir.resolve() / fname)
    if len(path) > MAX_IPC_PATH:
        raise StartupError(
            f"run directory path too long for ipc sockets: {path!r} has {len(path)} "
            f"bytes, expected at most {MAX_IPC_PATH}; use a shorter --run-dir"
        )
    return f"ipc://{path}"


def log_endpoint(run_dir: Path) -> str:
    """Where a process's nodes send their log records: log.sock in its run directory."""
    return _ipc_url(run_dir, _ENDPOINTS["log"])


def make_private(run_dir: Path) -> None:
    """Make run_dir (created if missing) its owner's alone, whatever the umask."""
    run_dir.mkdir(parents=True, exist_ok=True)
    st = run_dir.stat()
    if st.st_mode & stat.S_ISVTX or st.st_uid != os.geteuid():
        # /tmp and the like: closing them to everybody else would break other programs.
        raise StartupError(
            f"run directory {run_dir}: expected a directory of this user's own, got a shared "
            f"one (owner uid {st.st_uid}{', sticky bit' if st.st_mode & stat.S_ISVTX else ''})"
            f"; give --run-dir a new folder, e.g. {run_dir / 'run'}")
    os.chmod(run_dir, RUN_DIR_MODE)


def set_file_mode(path: Path | str) -> None:
    """Results and logs: the owner writes, the group reads, nobody else (whatever the umask)."""
    with contextlib.suppress(FileNotFoundError):
        os.chmod(path, FILE_MODE)


@dataclass(frozen=True)
class Endpoints:
    """Where every socket of one pipeline lives."""

    capture: str
    workers: str
    tap: str
    results_tap: str
    heartbeat: str
    control: str
    log: str
    orders: str
    capture_link: str
    workers_link: str
    results_link: str

    @classmethod
    def for_run(cls, net: NetworkConfig, run_dir: Path) -> Endpoints:
        """ipc:// files in the run directory, whatever network.transport says (see
        _ENDPOINTS); `net` stays in the signature, which every node and client calls."""
        urls = {name: _ipc_url(run_dir, fname) for name, fname in _ENDPOINTS.items()}
        for name, fname in _LINKS.items():
            urls[name] = str(run_dir.resolve() / fname)
        return cls(**urls)


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


TAP_RCVHWM = 64  # subscription messages queued from one peer before libzmq stops reading it
# After subscriptions were refused, the process trims its heap this often for this long: the
# memory libzmq held for them is freed when their sender leaves (TapGate.trim_due).
TRIM_INTERVAL_S = 5.0
TRIM_FOR_S = 60.0


class TapGate:
    """The subscriptions a bound tap (XPUB, xpub_manual) takes: only prefixes of its topics.

    A subscription that is no prefix of a topic would never match anything, so refusing it
    changes nothing for a reader; counts per prefix say which topics somebody reads. What
    the process keeps is bounded by the prefixes of a few short topics. (libzmq itself still
    records every subscription a connected peer sent, about 600 bytes each, until that peer
    disconnects; who may connect at all is the run directory's permissions' business.)
    """

    def __init__(self, sock: zmq.Socket[bytes], topics: Sequence[bytes]) -> None:
        self.sock = sock
        self.topics = tuple(topics)
        self._valid = {t[:i] for t in self.topics for i in range(len(t) + 1)}
        self.readers: dict[bytes, int] = {}
        self.refused = 0
        self._refused_seen = 0
        self._trim_until = 0.0  # trims are due until then (refused subscriptions came)
        self._next_trim = 0.0

    def drain(self) -> bool:
        """Take the subscription messages waiting (never blocks); True if readers changed."""
        changed = False
        while True:
            try:
                msg = self.sock.recv(zmq.NOBLOCK)
            except zmq.Again:
                return changed
            prefix = msg[1:]
            if msg[:1] not in (b"\x00", b"\x01") or prefix not in self._valid:
                self.refused += 1  # no topic starts so: it could never match
                continue
            if msg[:1] == b"\x01":
                self.sock.setsockopt(zmq.SUBSCRIBE, prefix)  # for the peer that sent it
                self.readers[prefix] = self.readers.get(prefix, 0) + 1
            else:
                self.sock.setsockopt(zmq.UNSUBSCRIBE, prefix)
                left = self.readers.get(prefix, 0) - 1
                if left > 0:
                    self.readers[prefix] = left
                else:
                    self.readers.pop(prefix, None)
            changed = True

    def trim_due(self, now: float) -> bool:
        """Whether the process should release freed memory now (runtime.node.release_memory):
        every TRIM_INTERVAL_S for TRIM_FOR_S after the last refused subscription, so what a
        hostile subscriber made libzmq hold goes back to the system once it leaves."""
        if self.refused != self._refused_seen:
            self._refused_seen = self.refused
            self._trim_until = now + TRIM_FOR_S
        if now < self._trim_until and now >= self._next_trim:
            self._next_trim = now + TRIM_INTERVAL_S
            return True
        return False

    def wanted(self, topic: bytes) -> bool:
        """Somebody reads topic (subscribed to a prefix of it)."""
        return any(topic.startswith(p) for p in self.readers)


# --- CURVE: keys, the authenticator, the handshake monitor ------------------------------

SERVER_KEY_NAME = "server.key"  # the pipeline's public key, in a remote worker's key folder
CLIENT_SECRET_NAME = "client.key_secret"  # a remote worker's own key pair, in the same folder


def load_key_file(path: Path, secret: bool) -> tuple[bytes, bytes | None]:
    """(public, secret) from a key file made by zmq.auth; StartupError naming the fix."""
    import zmq.auth

    kind = "secret key file (NAME.key_secret)" if secret else "public key file (NAME.key)"
    if not path.is_file():
        raise StartupError(f"expected a CURVE {kind} at {path}, got no such file; make one "
                           f"with `trapflow keys generate DIR`")
    try:
        public, sec = zmq.auth.load_certificate(str(path))
    except (OSError, ValueError) as exc:
        raise StartupError(f"expected a CURVE {kind} at {path}, got: {exc}; "
                           f"make one with `trapflow keys generate DIR`") from None
    if secret and not sec:
        raise StartupError(f"expected a CURVE {kind} at {path}, got a public key only; "
                           f"give the .key_secret file of `trapflow keys generate`")
    return public, sec


def server_keys(secret_file: Path) -> CurveKeys:
    """The pipeline's CURVE server keys (network.remote.server_key)."""
    public, secret = load_key_file(secret_file, secret=True)
    assert secret is not None
    return CurveKeys(public, secret)


def client_keys(folder: Path) -> CurveKeys:
    """A remote worker's keys: its own pair and the pipeline's public key, in one folder."""
    public, secret = load_key_file(folder / CLIENT_SECRET_NAME, secret=True)
    server, _ = load_key_file(folder / SERVER_KEY_NAME, secret=False)
    assert secret is not None
    return CurveKeys(public, secret, server)


def start_authenticator(ctx: zmq.Context[zmq.Socket[bytes]], authorized: Path) -> Any:
    """ZAP for every CURVE server socket of ctx: only the public keys in `authorized` pass.

    zmq.auth's ThreadAuthenticator answers handshakes from a thread of its own; it sees
    keys, never frames.
    """
    from zmq.auth.thread import ThreadAuthenticator

    if not authorized.is_dir():
        raise StartupError(f"network.remote.authorized_keys: expected a folder of public "
                           f"keys (*.key), got {authorized} (not a folder)")
    auth = ThreadAuthenticator(ctx)
    auth.start()
    auth.configure_curve(domain="*", location=str(authorized))
    return auth


# Handshake failures of a CURVE server socket, as the reason they are counted under.
HANDSHAKE_REFUSALS = {
    int(zmq.EVENT_HANDSHAKE_FAILED_AUTH): "remote_unauthorised_key",
    int(zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL): "remote_bad_handshake",
    int(zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL): "remote_bad_handshake",
}


def open_monitor(sock: zmq.Socket[bytes]) -> zmq.Socket[bytes]:
    """A PAIR socket that receives sock's refused handshakes (zmq's socket monitor)."""
    events = 0
    for ev in HANDSHAKE_REFUSALS:
        events |= ev
    mon: zmq.Socket[bytes] = sock.get_monitor_socket(events)
    mon.setsockopt(zmq.LINGER, 0)
    return mon


def read_monitor(mon: zmq.Socket[bytes]) -> list[str]:
    """The refusal reasons waiting on a monitor socket (never blocks)."""
    from zmq.utils.monitor import parse_monitor_message

    out: list[str] = []
    while zmq_readable(mon):
        event = parse_monitor_message(mon.recv_multipart())
        reason = HANDSHAKE_REFUSALS.get(int(event["event"]))
        if reason is not None:
            out.append(reason)
    return out


def new_context() -> zmq.Context[zmq.Socket[bytes]]:
    """The one context of a process (created in the process, never inherited)."""
    return zmq.Context()


# --- local links -------------------------------------------------------------------------
# ZeroMQ wakes two I/O threads per message; a descriptor is ~200 bytes, so on one host a
# UNIX seqpacket socket (one datagram per message, no extra threads) moves it ~5x cheaper.

class LinkClosed(TrapflowError):
    """The other end of a local link is gone (or was never there)."""


LINK_RETRY_S = 0.02  # how often a peer tries to reach a broker that is not listening (yet)
_LINK_SNDBUF = 4 << 20  # the kernel caps this at its own maximum; results are small anyway


class Link:
    """One end of a local link: non-blocking, a message is one datagram of frames."""

    def __init__(self, sock: socket.socket) -> None:
        sock.setblocking(False)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, _LINK_SNDBUF)
        self.sock = sock
        self._buf = bytearray(frame_msgs.MAX_LINK_BYTES)  # one datagram at a time, reused
        self._view = memoryview(self._buf)
        self._poll = select.poll()
        self._poll.register(sock.fileno(), select.POLLIN)

    def fileno(self) -> int:
        return self.sock.fileno()

    def send(self, frames: Sequence[messages.Buffer]) -> bool:
        """Send one message; False if the peer's queue is full (it is not sent)."""
        data = frame_msgs.pack_frames(frames)
        try:
            self.sock.send(data)
        except BlockingIOError:
            return False
        except OSError as exc:
            if exc.errno == errno.EMSGSIZE:
                raise ProtocolError(
                    f"link message: expected at most the socket buffer, got {len(data)} bytes"
                ) from None
            raise LinkClosed(f"local link closed: {exc}") from None
        return True

    def recv(self) -> list[memoryview] | None:
        """The next message's frames, or None if none is waiting; LinkClosed at EOF."""
        for _ in range(2):
            try:
                n = self.sock.recv_into(self._buf)
            except BlockingIOError:
                return None
            except ConnectionResetError:
                # The peer closed with messages of ours unread (a job sent to a worker that
                # was leaving). Linux reports that once, ahead of what the peer sent before
                # closing, which is still queued (its last answer, its goodbye): read on.
                continue
            except OSError as exc:
                raise LinkClosed(f"local link closed: {exc}") from None
            if n == 0:
                raise LinkClosed("local link closed by its peer")
            return frame_msgs.unpack_frames(bytes(self._view[:n]))
        raise LinkClosed("local link closed: reset by its peer")

    def wait(self, timeout_ms: int) -> bool:
        """True when a message (or EOF) is waiting, within timeout_ms."""
        return bool(self._poll.poll(timeout_ms))

    def wait_writable(self, timeout_ms: int) -> bool:
        """True when the peer's queue has room again, within timeout_ms."""
        out = select.poll()
        out.register(self.sock.fileno(), select.POLLOUT)
        return bool(out.poll(timeout_ms))

    def close(self) -> None:
        self.sock.close()


class LinkClient:
    """The connecting end of a local link: connects on first use, again after a drop.

    The broker may die and be restarted at any time; its successor listens at the same path.
    """

    def __init__(self, path: str) -> None:
        self.path = path
        self.link: Link | None = None

    def get(self) -> Link | None:
        """The connected link, or None while nobody listens (LINK_RETRY_S is a fair wait)."""
        if self.link is None:
            try:
                self.link = connect_link(self.path)
            except LinkClosed:
                return None
        return self.link

    def drop(self) -> None:
        """Forget a link whose peer went away; the next get() connects afresh."""
        if self.link is not None:
            self.link.close()
            self.link = None


def _check_path(path: str) -> None:
    if len(path) > MAX_IPC_PATH:
        raise StartupError(f"run directory path too long for local links: {path!r} has "
                           f"{len(path)} bytes, expected at most {MAX_IPC_PATH}; "
                           f"use a shorter --run-dir")


def listen_link(path: str) -> socket.socket:
    """A listening local link; a file left by a crashed predecessor is replaced."""
    _check_path(path)
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    sock.bind(path)
    os.chmod(path, SOCKET_MODE)  # before listen(): nobody else may connect
    sock.listen(64)
    sock.setblocking(False)
    return sock


def accept_link(listener: socket.socket) -> Link | None:
    """The next peer that connected, or None."""
    try:
        conn, _ = listener.accept()
    except BlockingIOError:
        return None
    return Link(conn)


def connect_link(path: str) -> Link:
    """Connect to a listening local link; LinkClosed if nobody listens there (yet)."""
    _check_path(path)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    try:
        sock.connect(path)
    except OSError as exc:
        sock.close()
        raise LinkClosed(f"cannot connect to {path}: {exc.strerror}") from None
    return Link(sock)


_EVENTS, _POLLIN = int(zmq.EVENTS), int(zmq.POLLIN)  # plain ints: no enum conversion


def zmq_readable(sock: zmq.Socket[bytes]) -> bool:
    """A message is waiting. Cheaper than a failed recv on a hot path, and reading
    EVENTS re-arms the socket's notification descriptor."""
    events = sock.getsockopt(_EVENTS)
    return isinstance(events, int) and bool(events & _POLLIN)


class Poller:
    """One poll() system call over local links, listeners and zmq sockets.

    zmq's own poller reads every zmq socket's events before and after it sleeps, a few
    system calls per socket on every pass; with the ring, a broker's per-pair traffic is
    on links alone. Here a zmq socket is watched through its notification descriptor
    (ZMQ_FD), which only says "something changed", so its events are read when that
    fired, or when this process used the socket since (touch()): any send or receive may
    consume the notification of a message that is waiting.
    """

    def __init__(self) -> None:
        self._poll = select.poll()
        self._zmq: dict[int, zmq.Socket[bytes]] = {}  # notification fd -> socket
        self._touched: set[zmq.Socket[bytes]] = set()

    def register(self, obj: zmq.Socket[bytes] | socket.socket | Link) -> None:
        if isinstance(obj, zmq.Socket):
            fd = obj.getsockopt(zmq.FD)
            assert isinstance(fd, int)
            self._zmq[fd] = obj
            self._touched.add(obj)  # what arrived before registering
        else:
            fd = obj.fileno()
        self._poll.register(fd, select.POLLIN)

    def unregister(self, obj: socket.socket | Link) -> None:
        self._poll.unregister(obj.fileno())

    def touch(self, sock: zmq.Socket[bytes]) -> None:
        """Read sock's events on the next poll: it was used since they were last read."""
        self._touched.add(sock)

    def poll(self, timeout_ms: int) -> tuple[list[zmq.Socket[bytes]], list[int]]:
        """The zmq sockets with a message waiting, and the other descriptors readable."""
        ready = [s for s in self._touched if zmq_readable(s)]
        self._touched.clear()
        socks: list[zmq.Socket[bytes]] = []
        fds: list[int] = []
        for fd, _ in self._poll.poll(0 if ready else timeout_ms):
            sock = self._zmq.get(fd)
            if sock is None:
                fds.append(fd)
            elif sock not in ready and zmq_readable(sock):
                socks.append(sock)
        return ready + socks, fds
