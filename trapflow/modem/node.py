"""The modem process: sends outbox records to the surface and adds health records, and
executes the surface's signed commands.

Owns a SUB of the broker's stats (pool rates, the ladder's level and capture's image-health
state for health: a change of level or of image state sends a health record at once) and a
REQ to the supervisor's control socket (trapflow.wire.control_client.ControlClient)
through which commands run. The serial port is opened and
re-opened by the sender; while it is missing the node is inactive with the reason, the
outbox keeps filling, and sending resumes when the port is back.
A command is checked by trapflow.modem.command.CommandGuard; its counter is saved (beside
the outbox, fsynced) before it runs; its reply goes out before any data.
"""

from __future__ import annotations

import logging
import secrets
import sqlite3
import time
from typing import Any

import zmq

from trapflow.errors import ConfigError, ProtocolError, unreachable
from trapflow.modem.command import (
    CommandGuard,
    CounterState,
    Execute,
    Refuse,
    Reply,
    control_request,
    describe,
    load_counter,
    load_key,
    save_counter,
    status_summary,
)
from trapflow.modem.frame import (
    CMD_HEALTH,
    CMD_KINDS,
    CMD_LEVEL,
    CMD_STATUS,
    REPLY_ERROR,
    REPLY_OK,
    Command,
)
from trapflow.modem.health import HealthMonitor
from trapflow.modem.outbox import OutboxFull
from trapflow.modem.sender import ModemSender
from trapflow.runtime.files import SpaceReserve, is_disk_full
from trapflow.runtime.node import ACTIVE, FINALIZED, INACTIVE, Node, NodeSpec
from trapflow.runtime.ratelog import RateLimitedLog, wire
from trapflow.wire import tap_msgs
from trapflow.wire.control_client import ControlClient
from trapflow.wire.transport import SocketSpec, open_socket

log = logging.getLogger(__name__)

OUTBOX_RESERVE = ".outbox.reserve"  # beside the outbox: space kept for a full disk
OUTBOX_RESERVE_BYTES = 1 << 20  # thousands of health records
COUNTER_FILE = "commands.json"  # beside the outbox: the last accepted surface command


class ModemNode(Node):
    """Runs ModemSender.step() between heartbeats."""

    def __init__(self, spec: NodeSpec) -> None:
        super().__init__(spec)
        self.stats_sub = open_socket(self.ctx, SocketSpec(
            zmq.SUB, self.endpoints.tap, subscribe=(tap_msgs.TOPIC_STATS,), rcvhwm=4))
        self.pools: dict[str, tuple[float, int]] = {}
        health = None
        if self.cfg.health.enabled or self.cfg.ladder.enabled:  # a level change: a record
            health = HealthMonitor(self.cfg.health, spec.run_dir, lambda: self.pools,
                                   self.cfg.energy)
        self.health = health
        outbox = spec.run_dir / self.cfg.outbox.path
        self.sender = ModemSender(outbox, self.cfg.modem.port, self.cfg.modem, self.cfg.outbox,
                                  health)
        mcfg = self.cfg.modem
        key = load_key(mcfg.command_key) if mcfg.command_key else None
        self.counter_path = outbox.with_name(COUNTER_FILE)
        try:
            state, disabled = load_counter(self.counter_path, self.sender.session), ""
        except ConfigError as exc:
            # Results must still reach the surface: only commands stop, none can be replayed.
            log.error("surface commands refused: %s", exc)
            state, disabled = CounterState(session=self.sender.session.hex()), str(exc)
        # A node started without a supervisor's run id is a start of its own.
        run = spec.run_id or secrets.token_hex(8)
        self.guard = CommandGuard(key, self.sender.session, state, run=run, disabled=disabled)
        self.control = ControlClient(self.ctx, self.endpoints.control)
        self.health_now = HealthMonitor(self.cfg.health, spec.run_dir, lambda: self.pools,
                                        self.cfg.energy)
        self.running: tuple[int, Command] | None = None
        self.ratelog = RateLimitedLog(log)
        # Space kept for the outbox's own writes (health records, acknowledgements) when the
        # run's disk fills up: freed at the first write the full disk refused.
        self.reserve = SpaceReserve(outbox.with_name(OUTBOX_RESERVE), OUTBOX_RESERVE_BYTES)
        self.disk_full = 0  # sender steps a full disk refused

    def counters(self) -> dict[str, int]:
        out = {k: v for k, v in self.sender.stats().items() if isinstance(v, int)}
        out.update({f"commands_{k}": n for k, n in self.guard.counts.items()})
        out["disk_full"] = self.disk_full
        return out

    def _step(self) -> float:
        """One sender step; a full disk is survived: the reserve is freed once (so health
        records can say what happened), the step counted, and tried again a second later."""
        try:
            return self.sender.step()
        except (OutboxFull, sqlite3.OperationalError) as exc:
            if not (isinstance(exc, OutboxFull) or is_disk_full(exc)):
                raise
            self.disk_full += 1
            freed = self.reserve.release()
            self.ratelog.log(logging.ERROR, "disk", "outbox: the disk is full (%s)%s", exc,
                               f"; freed the {freed} bytes kept for it" if freed else "")
            return 1.0

    def run(self) -> int:
        while not self.stopping:
            delay = self._step()
            st: dict[str, Any] = self.sender.stats()
            if st.get("state") == "active":
                self.set_state(ACTIVE)
            else:
                self.set_state(INACTIVE, str(st.get("reason", "")))
            self._commands(time.monotonic())
            self._read_stats()
            self.beat()
            self.sender.port.wait_readable(min(delay, 0.1))
        self.control.close()
        self.sender.close()
        self.set_state(FINALIZED)
        return 0

    # --- surface commands ----------------------------------------------------------------

    def _commands(self, now: float) -> None:
        for payload in self.sender.take_commands():
            d = self.guard.receive(payload, now)
            if isinstance(d, Refuse):
                # A retransmission of the running command is the link's doing, not an attack.
                level = logging.INFO if d.kind == "duplicates" else logging.WARNING
                self.ratelog.log(level, d.kind, "surface command refused: %s", wire(d.why))
            elif isinstance(d, Execute):
                self._execute(d, now)
            elif isinstance(d, Reply):
                self.sender.send_reply(d.payload, d.repeat)
            else:
                unreachable(d)
        if self.running is not None:
            reply = self.control.poll(now)
            if reply is not None:
                self._answered(reply)

    def _execute(self, d: Execute, now: float) -> None:
        cmd = d.command
        try:
            save_counter(self.counter_path, d.state)  # before it runs: never twice
        except OSError as exc:
            log.error("cannot save the command counter %s (%s): command %d not run",
                      self.counter_path, exc, d.counter)
            self._finish(d.counter, REPLY_ERROR, {"error": f"box cannot save its command "
                                                   f"counter: {exc}; not run"})
            return
        log.info("surface command %d: %s", d.counter, wire(describe(cmd)))
        if cmd.kind not in CMD_KINDS:
            self._finish(d.counter, REPLY_ERROR, {"error": cmd.text})
            return
        if cmd.kind == CMD_HEALTH:
            st = self.sender.stats()
            self._finish(d.counter, REPLY_OK,
                         self.health_now.sample(int(st.get("backlog", 0)), str(st["state"])))
            return
        req = control_request(cmd)
        assert req is not None
        self.running = (d.counter, cmd)
        try:
            self.control.send(req, self.cfg.modem.command_timeout_s, now)
        except zmq.ZMQError as exc:
            self.control.close()
            self._answered({"error": f"cannot reach the supervisor: {exc}"})

    def _answered(self, reply: dict[str, Any]) -> None:
        assert self.running is not None
        counter, cmd = self.running
        self.running = None
        if "error" in reply:
            self._finish(counter, REPLY_ERROR, {"error": str(reply["error"])})
        elif cmd.kind == CMD_STATUS:
            self._finish(counter, REPLY_OK, status_summary(reply))
        elif cmd.kind == CMD_LEVEL:  # the supervisor's answer to a LevelRequest
            self._finish(counter, REPLY_OK, {"level": str(reply.get("level", "")),
                                             "auto": bool(reply.get("auto")),
                                             "reason": str(reply.get("reason", ""))})
        else:
            self._finish(counter, REPLY_OK, {"changed": str(reply.get("changed", "")),
                                             "change": str(reply.get("change", ""))})

    def _finish(self, counter: int, status: int, data: dict[str, Any]) -> None:
        payload, state = self.guard.finished(counter, status, data)
        self._save(state)
        self.sender.send_reply(payload)
        log.info("surface command %d answered: %s", counter,
                 "ok" if status == REPLY_OK else wire(str(data.get("error", ""))))

    def _save(self, state: CounterState) -> None:
        try:
            save_counter(self.counter_path, state)
        except OSError as exc:  # the counter is saved already: only the reply cache is lost
            log.warning("cannot save the reply of command %d in %s: %s", state.counter,
                        self.counter_path, exc)

    def _read_stats(self) -> None:
        while True:
            try:
                frames = self.stats_sub.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return
            try:
                msg = tap_msgs.decode_tap(frames)
            except ProtocolError:
                continue
            if not isinstance(msg, tap_msgs.TapStats):
                continue
            stats = msg.stats
            self.pools = {n: (p.rate, p.dropped) for n, p in stats.pools.items()}
            if self.health is not None:
                self.health.set_level(stats.level)
                self.health.set_image(stats.image)
            self.health_now.level = stats.level  # a record asked for now says it too
            self.health_now.set_image(stats.image)
