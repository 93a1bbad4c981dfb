"""The only module that creates sockets: an endpoint table and SocketSpec -> open socket.

Sockets are opened inside the process that uses them (never inherited across a
fork), from that process's single context, with linger 0 so shutdown never hangs.
"""

from __future__ import annotations

import errno
from dataclasses import dataclass
from pathlib import Path

import zmq

from trapflow.config import NetworkConfig
from trapflow.errors import StartupError

# Linux limits a UNIX socket path to 107 bytes.
MAX_IPC_PATH = 107

# Name -> (ipc file name, tcp port offset). The supervisor, broker and normalizer bind these.
_ENDPOINTS = {
    "capture": ("capture.sock", 0),  # capture PUSH -> broker PULL
    "workers": ("workers.sock", 1),  # broker ROUTER <-> worker DEALERs
    "results": ("results.sock", 2),  # broker PUSH -> normalizer PULL
    "tap": ("tap.sock", 3),  # broker PUB: frames and stats
    "results_tap": ("results-tap.sock", 4),  # normalizer PUB: JSON results
    "heartbeat": ("heartbeat.sock", 5),  # nodes PUSH -> supervisor PULL
    "control": ("control.sock", 6),  # supervisor REP: status, stop
}


@dataclass(frozen=True)
class Endpoints:
    """Where every socket of one pipeline lives."""

    capture: str
    workers: str
    results: str
    tap: str
    results_tap: str
    heartbeat: str
    control: str

    @classmethod
    def for_run(cls, net: NetworkConfig, run_dir: Path) -> Endpoints:
        """ipc:// files in the run directory, or consecutive tcp ports on the loopback host."""
        urls: dict[str, str] = {}
        for name, (fname, offset) in _ENDPOINTS.items():
            if net.transport == "ipc":
                path = str(run_dir.resolve() / fname)
                if len(path) > MAX_IPC_PATH:
                    raise StartupError(
                        f"run directory path too long for ipc sockets: {path!r} has {len(path)} "
                        f"bytes, expected at most {MAX_IPC_PATH}; use a shorter --run-dir"
                    )
                urls[name] = f"ipc://{path}"
            else:
                urls[name] = f"tcp://{net.host}:{net.base_port + offset}"
        return cls(**urls)


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
    for topic in spec.subscribe:
        sock.setsockopt(zmq.SUBSCRIBE, topic)
    try:
        if spec.bind:
            sock.bind(spec.endpoint)
        else:
            sock.connect(spec.endpoint)
    except zmq.ZMQError as exc:
        sock.close(linger=0)
        verb = "bind" if spec.bind else "connect to"
        if exc.errno == errno.EADDRINUSE:
            raise StartupError(f"cannot {verb} {spec.endpoint}: address already in use") from None
        raise StartupError(f"cannot {verb} {spec.endpoint}: {exc}") from None
    return sock


def new_context() -> zmq.Context[zmq.Socket[bytes]]:
    """The one context of a process (created in the process, never inherited)."""
    return zmq.Context()
