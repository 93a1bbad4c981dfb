"""Local links: the UNIX seqpacket sockets that carry shared-memory descriptors on one host,
and one poller over links and ZeroMQ sockets."""

from __future__ import annotations

import contextlib
import errno
import os
import select
import socket
from collections.abc import Sequence

import zmq

from trapflow.errors import ProtocolError, StartupError, TrapflowError
from trapflow.wire import frame_msgs, messages
from trapflow.wire.endpoints import MAX_IPC_PATH, SOCKET_MODE
from trapflow.wire.transport import zmq_readable

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
