"""The names peers go by on the broker's ROUTER sockets: a local worker, a remote worker
and the supervisor of remote workers on another host."""

from __future__ import annotations


def worker_identity(pool: str, index: int, pid: int) -> str:
    """The routing identity of one worker process (new with every restart)."""
    return f"{pool}:{index}:{pid}"


def remote_identity(pool: str, host: str, index: int, pid: int) -> str:
    """The routing identity of a worker process on another host: never a local one's
    (those have no '@'), so a remote peer cannot answer for a local worker."""
    return f"{pool}@{host}:{index}:{pid}"


def owner_identity(host: str, pid: int) -> str:
    """The identity of a `trapflow worker` supervisor on another host."""
    return f"owner@{host}:{pid}"
