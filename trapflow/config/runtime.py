"""The runtime's sections: the supervisor, the log file, remote workers, the network and the
viewer."""

from __future__ import annotations

import ipaddress
from typing import Annotated, Literal

import msgspec

from trapflow.config.base import Section as _Section


class SupervisorConfig(_Section):
    """Heartbeats, restarts and the stop ladder."""

    heartbeat_interval_s: Annotated[float, msgspec.Meta(gt=0, le=60)] = 1.0
    """Every node sends a heartbeat this often."""
    liveness_s: Annotated[float, msgspec.Meta(gt=0, le=600)] = 5.0
    """A node (or a remote worker host) silent this long is taken for dead: restarted, or its
    workers evicted (a worker busy with a pair: its pool's timeout_s)."""
    restart_backoff_s: Annotated[float, msgspec.Meta(ge=0, le=60)] = 0.5
    """First restart delay, doubled at each restart."""
    restart_backoff_max_s: Annotated[float, msgspec.Meta(ge=0, le=600)] = 10.0
    """Longest restart delay."""
    max_restarts: Annotated[int, msgspec.Meta(ge=0)] = 5
    """Restarts of a node allowed within restart_window_s before it is given up."""
    restart_window_s: Annotated[float, msgspec.Meta(gt=0)] = 60.0
    """The window in which max_restarts are counted."""
    retry_cooldown_s: Annotated[float, msgspec.Meta(ge=0, le=86400)] = 60.0
    """A node given up (its restart budget spent) is retried this long after, with a fresh
    budget; essential nodes (broker, capture, normalizer) are never given up."""
    stop_timeout_s: Annotated[float, msgspec.Meta(gt=0, le=4)] = 2.0
    """Stop ladder: a node asked to stop has this long before it is killed."""
    startup_timeout_s: Annotated[float, msgspec.Meta(gt=0, le=3600)] = 60.0
    """How long every node has to report its first state before start-up is declared
    failed; more on a slow board or under emulation, where imports and the synthetic
    world's set-up take minutes."""


class LogFileConfig(_Section):
    """trapflow.log in the run directory: rotated at max_bytes, keeping `backups` old files."""

    max_bytes: Annotated[int, msgspec.Meta(ge=65536)] = 10 << 20
    """trapflow.log is rotated when it reaches this size."""
    backups: Annotated[int, msgspec.Meta(ge=1, le=100)] = 3
    """Old logs kept (trapflow.log.1 .. trapflow.log.N)."""


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


class RemoteConfig(_Section):
    """Where worker pools on other hosts connect (`trapflow worker --connect`), and the
    CURVE keys that guard it. Off while `bind` is empty."""

    bind: str = ""
    """tcp://HOST:PORT the broker binds for remote workers; beyond loopback only with keys."""
    server_key: str = ""
    """The pipeline's secret key file (NAME.key_secret from `trapflow keys generate`)."""
    authorized_keys: str = ""
    """Folder of the public keys (*.key) of the workers that may connect."""

    def __post_init__(self) -> None:
        if bool(self.server_key) != bool(self.authorized_keys):
            raise ValueError(
                "expected both server_key and authorized_keys (CURVE) or neither, got only "
                f"{'server_key' if self.server_key else 'authorized_keys'}; "
                "make keys with `trapflow keys generate DIR`")
        if not self.bind:
            return
        scheme, sep, rest = self.bind.partition("://")
        host, colon, port = rest.rpartition(":")
        if scheme != "tcp" or not sep or not colon or not host or not port.isdigit() or not (
                1024 <= int(port) <= 65535):
            raise ValueError(f"expected bind as tcp://HOST:PORT with a port in 1024..65535, "
                             f"got {self.bind!r}")
        if not _is_loopback(host.strip("[]")) and not self.server_key:
            raise ValueError(
                f"binding {self.bind!r} beyond loopback needs CURVE keys: expected "
                "server_key and authorized_keys, got none; make them with "
                "`trapflow keys generate DIR` or bind tcp://127.0.0.1:PORT")

    @property
    def curve(self) -> bool:
        """Remote workers must prove a key in authorized_keys."""
        return bool(self.server_key)


class NetworkConfig(_Section):
    """Endpoints: ipc:// files in the run directory, reachable only by its owner; remote
    workers connect to a TCP port of their own (`remote`), guarded by CURVE keys."""

    transport: Literal["ipc", "tcp"] = "ipc"
    """Kept for older configs: since issue 26 item 3 `tcp` puts nothing on TCP ports (other
    local users read frames and forged results there); every local socket is ipc."""
    host: str = "127.0.0.1"
    """Kept for older configs: a loopback address only (the pipeline's endpoints never leave the
    host)."""
    base_port: Annotated[int, msgspec.Meta(ge=1024, le=65000)] = 5550
    """Kept for older configs; no socket uses it (see transport)."""
    remote: RemoteConfig = msgspec.field(default_factory=RemoteConfig)

    def __post_init__(self) -> None:
        if not _is_loopback(self.host):
            raise ValueError(
                f"expected a loopback host (127.0.0.1), got {self.host!r}: the pipeline's own "
                "endpoints never leave this host; workers on other hosts connect to "
                "network.remote.bind, guarded by CURVE keys"
            )


class ViewerConfig(_Section):
    """The live web viewer and its metrics (`trapflow start --view`, `trapflow view`)."""

    enabled: bool = False
    """Run the viewer as a node of the pipeline."""
    host: str = "127.0.0.1"
    """Address the web page binds to; loopback unless you mean to show it to the network."""
    port: Annotated[int, msgspec.Meta(ge=1, le=65535)] = 8090
    """TCP port of the web page and of /metrics."""
    frame_hz: Annotated[float, msgspec.Meta(gt=0, le=15)] = 2.0
    """Pairs per second shown in the page: the broker makes a small preview this often,
    and only while a page is open."""
    metrics_file: str = ""
    """node_exporter textfile written atomically every metrics_interval_s ("" = none)."""
    metrics_interval_s: Annotated[float, msgspec.Meta(ge=1, le=600)] = 5.0
    """Seconds between two writes of metrics_file."""
    allowed_hosts: list[str] = []
    """Host names the page may be reached by besides the loopback names (and, off loopback,
    the bind address, this machine's name and IP addresses): any other Host is refused, so a
    DNS-rebinding page cannot read or drive the viewer."""
    token_file: str = ""
    """File holding the token every bind asks for, loopback included (mode 600, at least 16
    characters); "" = the environment's TRAPFLOW_VIEWER_TOKEN, else a new token each start,
    held in memory and printed once with the URL on the starting console."""
