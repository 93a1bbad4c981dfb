"""Requests to the supervisor's control socket (status, stop, pool and parameter changes,
ladder levels), the log records nodes send it, and their decoders, bounded."""

from __future__ import annotations

from typing import Annotated

import msgspec

from trapflow.errors import ProtocolError
from trapflow.wire.messages import (
    MAX_HEADER_BYTES,
    MAX_LOG_BYTES,
    Buffer,
    ControlName,
    Msg,
    ParamValue,
    PolicyText,
    decode_bounded,
)


class StatusRequest(Msg, frozen=True, tag="status"):
    """Ask the supervisor for the pipeline's nodes, states and counters."""


class StopRequest(Msg, frozen=True, tag="stop"):
    """Ask the supervisor to stop the pipeline."""


class PoolRequest(Msg, frozen=True, tag="pool"):
    """Change one pool at run time: exactly one of count, policy, active."""

    pool: ControlName
    count: Annotated[int, msgspec.Meta(ge=1, le=64)] | None = None
    policy: PolicyText | None = None
    active: bool | None = None


class ParamRequest(Msg, frozen=True, tag="param"):
    """Set one plugin parameter of a pool at run time (its workers are reconfigured)."""

    pool: ControlName
    key: ControlName
    value: ParamValue


class LevelRequest(Msg, frozen=True, tag="level"):
    """Force the degradation ladder to a level by name, or `auto` to let the triggers decide."""

    level: str


ControlRequest = StatusRequest | StopRequest | PoolRequest | ParamRequest | LevelRequest


_control_dec = msgspec.msgpack.Decoder(ControlRequest)


def decode_control(data: Buffer) -> ControlRequest:
    """Decode a control request (a pool change names exactly one change)."""
    req: ControlRequest = decode_bounded(_control_dec, data, "control request", MAX_HEADER_BYTES)
    if isinstance(req, PoolRequest):
        _check_one_change(req, "control request")
    return req


def _check_one_change(req: PoolRequest, what: str) -> None:
    given = [k for k in ("count", "policy", "active") if getattr(req, k) is not None]
    if len(given) != 1:
        raise ProtocolError(f"{what}: a pool change names exactly one of count, policy, "
                            f"active; got {given or 'none'} for pool {req.pool!r}: send one "
                            f"change per request")


_pool_json_dec = msgspec.json.Decoder(PoolRequest)


def decode_pool_change(data: Buffer) -> PoolRequest:
    """A pool change as JSON (the viewer's page): {"pool": NAME, and one of "count": N,
    "policy": P, "active": true|false}."""
    req: PoolRequest = decode_bounded(_pool_json_dec, data, "pool change", MAX_HEADER_BYTES)
    _check_one_change(req, "pool change")
    return req


class LogEntry(Msg, frozen=True, tag="log"):
    """One log record a node sends to the supervisor's log listener (never pickled)."""

    name: str  # the logger's name
    levelno: int
    process: str  # the node's name, e.g. "worker:mono:1"
    pid: int
    created: float  # wall clock, a label only
    message: str  # the formatted message, with any traceback appended
    console_once: bool = False  # said once on the console however many nodes say it


_log_dec = msgspec.msgpack.Decoder(LogEntry)


def decode_log(data: Buffer) -> LogEntry:
    """Decode a LogEntry a node sent to the supervisor's log listener."""
    entry: LogEntry = decode_bounded(_log_dec, data, "log record", MAX_LOG_BYTES)
    return entry
