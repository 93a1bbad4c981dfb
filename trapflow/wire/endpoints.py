"""Where the pipeline's sockets live: the endpoint table (ipc files in the run directory, 0700,
sockets 0600), the local links' paths, the log endpoint, the run directory's and files'
modes, and the check that a TCP-mode run's ports are free."""

from __future__ import annotations

import contextlib
import os
import socket
import stat
from dataclasses import dataclass
from pathlib import Path

from trapflow.config.schema import NetworkConfig
from trapflow.errors import StartupError

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
