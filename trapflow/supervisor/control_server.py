"""Runtime control of a running pipeline, the supervisor's two control sockets.

Control owns the REP control socket (status, stop, pool, param and level requests, and
their replies); BrokerLink owns the PUSH of orders that tells the broker what was decided
(pool switches, the ladder's level, workers gone, a planned stop), each sealed with the
run's order key (control_msgs.seal_order). The decisions are the core's.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import msgspec
import zmq

from trapflow.errors import ProtocolError, unreachable
from trapflow.runtime.lifecycle import Lifecycle
from trapflow.runtime.ratelog import RateLimitedLog, wire
from trapflow.supervisor.actions import Action, Refused
from trapflow.supervisor.pool_control import PoolControl
from trapflow.supervisor.state import SupervisorState
from trapflow.wire import control_msgs, messages

log = logging.getLogger(__name__)

# The broker's stats may predate a switch told to it this long ago (published once a second):
# only older switches are reconciled, so a change is not sent twice.
RECONCILE_AFTER_S = 2.0


class Control:
    """Answers the control socket: each request is decided by the core, applied by `act`,
    and answered with one JSON reply (`status` builds the status reply)."""

    def __init__(self, sock: zmq.Socket[bytes], core: SupervisorState, ratelog: RateLimitedLog,
                 *, status: Callable[[], dict[str, Any]], stop: Callable[[], None],
                 act: Callable[[Sequence[Action], float], None],
                 reconfigurable: Callable[[str], bool]) -> None:
        self.sock = sock
        self.core = core
        self.ratelog = ratelog
        self.status = status
        self.stop = stop
        self.act = act
        self.reconfigurable = reconfigurable

    def on_request(self, data: bytes) -> None:
        """One request (its first frame is `data`) read whole, acted on, and answered."""
        # A request is read whole: REP answers only after its last frame (else EFSM, exit 1).
        extra = 0
        while self.sock.getsockopt(zmq.RCVMORE):
            self.sock.recv()
            extra += 1
        try:
            if extra:
                raise ProtocolError(f"control request: expected 1 frame, got {extra + 1}; "
                                    f"send one encoded StatusRequest or StopRequest")
            req = control_msgs.decode_control(data)
        except ProtocolError as exc:
            self.ratelog.warning("control", "refused a control request: %s", wire(str(exc)))
            self.sock.send(msgspec.json.encode({"error": str(exc)}))
            return
        if isinstance(req, control_msgs.StopRequest):
            self.stop()
            self.sock.send(msgspec.json.encode({"stopping": True}))
        elif isinstance(req, (control_msgs.PoolRequest, control_msgs.ParamRequest)):
            self.sock.send(msgspec.json.encode(self._change(req)))
        elif isinstance(req, control_msgs.LevelRequest):
            self.sock.send(msgspec.json.encode(self._force_level(req.level)))
        elif isinstance(req, control_msgs.StatusRequest):
            self.sock.send(msgspec.json.encode(self.status()))
        else:
            unreachable(req)

    def _change(self, req: control_msgs.PoolRequest | control_msgs.ParamRequest) -> dict[str, Any]:
        """A runtime change: the core decides, this applies; the reply says what changed."""
        now = time.monotonic()
        try:
            if isinstance(req, control_msgs.ParamRequest):
                in_place = req.pool in self.core.pools.by_name and self.reconfigurable(req.pool)
                actions = self.core.pools.set_param(req.pool, req.key, req.value, now, in_place)
            elif req.count is not None:
                actions = self.core.pools.set_count(req.pool, req.count, now)
            elif req.policy is not None:
                actions = self.core.pools.set_policy(req.pool, req.policy, now)
            else:
                actions = self.core.pools.set_active(req.pool, bool(req.active), now)
        except Refused as exc:
            log.warning("refused a control change: %s", exc)
            return {"error": str(exc)}
        change = self.core.timeline[-1]
        log.info("control: %s %s", change.node, change.reason)
        self.act(actions, now)
        return {"changed": change.node, "change": change.reason,
                "pool": self.core.pools.pool_view()[req.pool]}

    def _force_level(self, level: str) -> dict[str, Any]:
        """`trapflow level NAME|auto`: the core decides, this applies; the reply says the
        level, whether it is forced and why (or the error)."""
        now = time.monotonic()
        try:
            actions = self.core.pools.force_level(level, now)
        except Refused as exc:
            log.warning("refused a level change: %s", wire(str(exc)))
            return {"error": str(exc)}
        if not actions:
            log.info("ladder: %s", self.core.timeline[-1].reason)
        self.act(actions, now)
        view = self.core.pools.ladder_view()
        assert view is not None
        return {"level": view["level"], "auto": not view["forced"], "reason": view["reason"]}


class BrokerLink:
    """What the supervisor tells the broker, never blocking: a send the broker cannot take
    now is logged, and reconcile() sends pool states and the level again from its stats."""

    def __init__(self, sock: zmq.Socket[bytes], key: bytes) -> None:
        self.sock = sock
        self.key = key  # the run's order key, the broker's too (NodeSpec.order_key)
        self.switched_at = 0.0  # when the broker was last told of a pool switch or level

    def _send(self, order: control_msgs.SupervisorOrder) -> None:
        """zmq.Again when the broker cannot take it now."""
        self.sock.send_multipart(control_msgs.seal_order(self.key, order), zmq.NOBLOCK)

    def gone(self, worker: str, reason: str) -> None:
        """A worker process died or left: the broker drops its pairs at once."""
        try:
            self._send(messages.Gone(worker=worker, reason=reason))
        except zmq.Again:
            pass  # the broker's own timeout will evict it

    def stopping(self) -> None:
        """A planned stop begins: workers leave from now on, a send to one that left is no
        news."""
        try:
            self._send(messages.Stopping())
        except zmq.Again:
            pass  # the broker is busy; a departure is then logged as a warning

    def switch_pool(self, pool: str, active: bool | None, policy: str | None,
                    params: Mapping[str, Any] | None = None,
                    min_interval_s: float | None = None) -> None:
        """A pool becomes (in)active, takes a new policy, parameters or minimum interval."""
        self.switched_at = time.monotonic()
        try:
            self._send(messages.PoolSwitch(
                pool=pool, active=active, policy=policy,
                params=dict(params) if params is not None else None,
                min_interval_s=min_interval_s))
        except zmq.Again:
            log.warning("could not tell the broker about pool %s now; status reconciles it",
                        pool)

    def level(self, pools: PoolControl) -> None:
        """The ladder's level to the broker, which publishes it in its stats (status, the
        viewer, and the modem node, which sends a health record when it changes)."""
        view = pools.ladder_view()
        if view is None:
            return
        self.switched_at = time.monotonic()
        try:
            self._send(messages.LadderLevel(level=view["level"], reason=view["reason"][:256]))
        except zmq.Again:
            log.warning("could not tell the broker the ladder's level now; status reconciles it")

    def reconcile(self, pools: PoolControl, stats: messages.Stats | None) -> None:
        """A restarted broker starts every pool active, with no minimum interval and no
        level: tell it again what runtime control and the ladder decided."""
        if time.monotonic() - self.switched_at < RECONCILE_AFTER_S:
            return  # its stats may not show the latest switch yet
        for name, p in pools.by_name.items():
            seen = stats.pools.get(name) if stats is not None else None
            want = p.state == Lifecycle.ACTIVE
            if seen is not None and seen.active != want:
                self.switch_pool(name, want, None)
            if seen is not None and seen.min_interval_s != p.min_interval_s:
                self.switch_pool(name, None, None, min_interval_s=p.min_interval_s)
        view = pools.ladder_view()
        if stats is not None and view is not None and stats.level != view["level"]:
            self.level(pools)
