"""Requests to the supervisor's control socket (status, stop, pool and parameter changes,
ladder levels), the log records nodes send it, the supervisor's sealed orders to the
broker, and their decoders, bounded."""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import Sequence
from typing import Annotated

import msgspec

from trapflow.errors import ProtocolError
from trapflow.wire.messages import (
    MAX_HEADER_BYTES,
    MAX_LOG_BYTES,
    Buffer,
    ControlName,
    Gone,
    LadderLevel,
    Msg,
    ParamValue,
    PolicyText,
    PoolSwitch,
    Stopping,
    decode_bounded,
    encode,
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


# --- the supervisor's orders to the broker -------------------------------------------------
# They ride a socket of their own (Endpoints.orders, an ipc file in the 0700 run directory),
# never the workers' socket, and each is sealed with the run's order key, which only the
# supervisor and the broker hold (handed in the spawn, never on a command line or in the
# environment): a process of the same user that reaches the socket still cannot forge one.

SupervisorOrder = Gone | Stopping | PoolSwitch | LadderLevel
ORDER_KEY_BYTES = 32
_order_dec = msgspec.msgpack.Decoder(SupervisorOrder)


def _seal(key: bytes, body: bytes) -> bytes:
    return hmac.new(key, body, hashlib.sha256).digest()


def seal_order(key: bytes, order: SupervisorOrder) -> list[bytes]:
    """[seal, order]: the frames the supervisor sends the broker."""
    body = encode(order)
    return [_seal(key, body), body]


def open_order(key: bytes, frames: Sequence[Buffer]) -> SupervisorOrder:
    """The order in [seal, order] frames; ProtocolError when it is not sealed with `key`."""
    if len(frames) != 2:
        raise ProtocolError(f"supervisor order: expected 2 frames [seal, order], got "
                            f"{len(frames)}")
    seal, body = (bytes(memoryview(f.buffer if hasattr(f, "buffer") else f)) for f in frames)
    if len(key) != ORDER_KEY_BYTES or not hmac.compare_digest(seal, _seal(key, body)):
        raise ProtocolError("supervisor order: its seal is not the run's (only the "
                            "supervisor that started this broker holds the key)")
    order: SupervisorOrder = decode_bounded(_order_dec, body, "supervisor order",
                                            MAX_HEADER_BYTES)
    return order
