"""The supervisor (`trapflow start`): boots the process graph, watches it, restarts, stops.

Owns a PULL of heartbeats from every node and a SUB of the broker's stats; its REP control
socket and DEALER to the broker are trapflow.supervisor.control_server's, the PULL of every node's
log records trapflow.supervisor.setup's (in its own thread). The whole graph is in boot().
The decisions are trapflow.supervisor.state's and the counting trapflow.supervisor.ledger's: this
shell turns processes, sockets and time into their events, and their actions into effects;
what it reports (status, status line, ledger.json) is trapflow.supervisor.report's.
"""

from __future__ import annotations

import logging
import os
import secrets
import signal
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import IO, Any

import msgspec
import zmq

from trapflow import registry
from trapflow.calibration.camera import StereoRig
from trapflow.config.schema import Config
from trapflow.errors import EXIT_FAILURE, EXIT_OK, ProtocolError, StartupError, unreachable
from trapflow.power.cpu import CpuMeter
from trapflow.power.schedule import WindowClock
from trapflow.runtime import forkserver, sdnotify
from trapflow.runtime.clock_step import ClockSteps
from trapflow.runtime.lifecycle import RECYCLE_EXITS
from trapflow.runtime.node import NodeSpec, node_main
from trapflow.runtime.ratelog import RateLimitedLog, wire
from trapflow.supervisor import ledger as run_ledger
from trapflow.supervisor.actions import (
    Action,
    AddWorker,
    Budget,
    GiveUp,
    Kill,
    LevelChanged,
    NodePlan,
    Reconfigure,
    Retire,
    Retry,
    Spawn,
    Stop,
    SwitchPool,
    WorkerGone,
)
from trapflow.supervisor.control_server import BrokerLink, Control
from trapflow.supervisor.ladder import Ladder
from trapflow.supervisor.ledger import RunLedger
from trapflow.supervisor.report import NodeView, Report, Snapshot
from trapflow.supervisor.sensors import Sensors
from trapflow.supervisor.setup import (
    RunLogging,
    clear_run_dir,
    create_ring,
    link_latest,
    lock_run_dir,
    preflight,
)
from trapflow.supervisor.state import DurationClock, SupervisorState, died_at_start
from trapflow.viewer.access import console_address, new_token
from trapflow.wire import control_msgs, identity, messages, tap_msgs
from trapflow.wire.endpoints import Endpoints, check_ports_free, make_private
from trapflow.wire.frame_ring import FrameRing
from trapflow.wire.transport import SocketSpec, new_context, open_socket

log = logging.getLogger(__name__)

# Stop ladder: capture first (no new pairs), then workers and broker, the normalizer last.
STOP_ORDER = ("viewer", "capture", "worker", "events", "broker", "normalizer", "modem")
SEQ_RESTART_GAP = 100  # extra seqs skipped at a capture restart, beyond the heartbeat lag


@dataclass
class Child:
    """One supervised process: its spec, its process, and its last counters."""

    spec: NodeSpec
    proc: Any = None  # multiprocessing.Process
    counters: dict[str, int] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.spec.name

    def alive(self) -> bool:
        return self.proc is not None and self.proc.is_alive()


def _budget(cfg: Config) -> Budget:
    sup = cfg.supervisor
    return Budget(max_restarts=sup.max_restarts, window_s=sup.restart_window_s,
                  backoff_s=sup.restart_backoff_s, backoff_max_s=sup.restart_backoff_max_s,
                  cooldown_s=sup.retry_cooldown_s)


def worker_liveness(timeout_s: float, heartbeat_interval_s: float) -> float:
    """Silence allowed to a worker: its pool's timeout_s (a worker beats as it takes a pair,
    so silence is time on one pair), but never under two idle heartbeats."""
    return max(timeout_s, 2 * heartbeat_interval_s)


class Supervisor:
    """Lifecycle manager of one pipeline."""

    def __init__(self, cfg: Config, run_dir: Path, duration: float | None = None,
                 out: IO[str] | None = None, latest: bool = False,
                 window: WindowClock | None = None) -> None:
        self.cfg = cfg
        self.run_dir = run_dir
        self.latest = latest  # point runs/latest at run_dir once the run starts
        self.started = False  # capture spawned: the run exists, whatever happens next
        self.duration = duration
        self.window = window  # the schedule's recording window: the run stops at its end
        self.window_ended = False
        self.out = out or sys.stdout
        self.mp = forkserver.node_context(run_dir)
        self.children: list[Child] = []
        # The decisions (filled by boot()); the ladder's readings are the sensors' below.
        self.core = SupervisorState((), _budget(cfg),
                                    ladder=Ladder(cfg.ladder) if cfg.ladder.enabled else None)
        self.ledger_model = RunLedger()  # the counters (status line, status, ledger.json)
        self.stop_requested = False
        self.planned_stop = False  # a duration, stop request, signal or drained source
        self.exit_code = EXIT_OK
        self.failure: str | None = None  # one line: why the run failed (exit status 1)
        self.t0 = time.monotonic()
        self.rig: StereoRig | None = None  # decided at preflight (trapflow.sources.rig)
        self.rig_origin = ""
        self.source_where = ""  # what the source reads (a recording's image topics)
        self.tag_size_m: float | None = None  # the tags the source lays, where it knows
        self.ring: FrameRing | None = None
        self.run_id = secrets.token_hex(8)  # this start; the modem's cached replies name it
        # Seals the orders to the broker: only a process handed it in the spawn can send one.
        self.order_key = secrets.token_bytes(control_msgs.ORDER_KEY_BYTES)
        # The viewer's token: in memory here and in the viewer's spawn spec, printed once.
        self.viewer_token = new_token() if cfg.viewer.enabled else ""
        self.notifier = sdnotify.Notifier()  # READY/WATCHDOG/STATUS under systemd, else no-op
        self.ratelog = RateLimitedLog(log)  # warnings about messages from sockets
        self.cpu = CpuMeter()  # CPU per role: the energy estimate in ledger.json
        self.clock_steps = ClockSteps()  # wall-clock steps, said once each
        # status reply, status line, ledger.json, totals
        self.report = Report(cfg, run_dir, self.out, self.t0, self.core, self.ledger_model,
                             self.report_snapshot)
        # The degradation ladder: its decisions are the core's, its readings these sensors'.
        self.sensors: Sensors | None = None
        if cfg.ladder.enabled:
            self.sensors = Sensors(cfg.ladder.sensors, run_dir)

    # --- the process graph --------------------------------------------------------------

    def boot(self) -> None:
        """Consumers first so nothing sent is lost: normalizer, broker, workers; capture is
        spawned once they are all active (see run())."""
        sup, cfg, run = self.cfg.supervisor, self.cfg, self.run_dir
        if self.rig is not None:
            log.info("rig from %s: %s", self.rig_origin, self.rig.describe())
        ring = self.ring.name if self.ring is not None else ""
        self._add(NodeSpec("normalizer", "normalizer", cfg, run, ring=ring), sup.liveness_s)
        if cfg.modem.enabled:
            self._add(NodeSpec("modem", "modem", cfg, run, ring=ring, run_id=self.run_id),
                      sup.liveness_s)
        self._add(NodeSpec("broker", "broker", cfg, run, ring=ring, rig=self.rig,
                           order_key=self.order_key), sup.liveness_s)
        if cfg.events.enabled:
            self._add(NodeSpec("events", "events", cfg, run, ring=ring), sup.liveness_s)
        for pool, pcfg in cfg.pools.items():
            if pcfg.count:  # runtime control (trapflow pool / param) knows the pools run
                self.core.pools.add_pool(pool, pcfg.count, pcfg.policy, pcfg.params,
                                         worker_liveness(pcfg.timeout_s, sup.heartbeat_interval_s),
                                         sup.startup_timeout_s)
            for i in range(pcfg.count):
                spec = NodeSpec("worker", f"worker:{pool}:{i}", cfg, run, pool=pool, index=i,
                                rig=self.rig, tag_size_m=self.tag_size_m, ring=ring)
                self._add(spec, worker_liveness(pcfg.timeout_s, sup.heartbeat_interval_s))
        self._add(NodeSpec("capture", "capture", cfg, run, rig=self.rig, ring=ring),
                  sup.liveness_s)
        now = time.monotonic()
        if cfg.viewer.enabled:  # reads the taps and the control socket like `trapflow view`
            self._add(NodeSpec("viewer", "viewer", cfg, run, viewer_token=self.viewer_token),
                      sup.liveness_s)
        for child in self.children:
            if child.spec.role != "capture":
                self._spawn(child, now)

    def _add(self, spec: NodeSpec, liveness_s: float) -> None:
        self.children.append(Child(spec))
        self.core.add(NodePlan(spec.name, spec.role, liveness_s, pool=spec.pool,
                               startup_s=spec.cfg.supervisor.startup_timeout_s))

    def _spawn(self, child: Child, now: float) -> None:
        child.proc = self.mp.Process(
            target=node_main, args=(child.spec, os.getpid()),
            name=child.name, daemon=False,
        )
        child.proc.start()
        child.counters = {}
        self.core.spawned(child.name, child.proc.pid, now)

    # --- main loop ---------------------------------------------------------------------

    def run(self) -> int:
        """Start, supervise until stopped, stop; return the exit status."""
        make_private(self.run_dir)
        lock = lock_run_dir(self.run_dir)
        results = self.run_dir / self.cfg.normalizer.results_file
        if results.exists():  # a reused run directory: this run's results start at its end
            self.ledger_model.delivered.offset = results.stat().st_size
            self.ledger_model.results_from = self.ledger_model.delivered.offset
        self.ctx = new_context()
        self.run_log: RunLogging | None = None
        try:
            found = preflight(self.cfg)
            self.rig, self.rig_origin, self.source_where = found.rig, found.origin, found.where
            self.tag_size_m = found.tag_size_m
            self.endpoints = Endpoints.for_run(self.cfg.network, self.run_dir)
            self.run_log = RunLogging(self.ctx, self.endpoints.log, self.run_dir, self.cfg)
            self.hb = open_socket(self.ctx, SocketSpec(zmq.PULL, self.endpoints.heartbeat,
                                                       bind=True))
            self.control = Control(
                open_socket(self.ctx, SocketSpec(zmq.REP, self.endpoints.control, bind=True)),
                self.core, self.ratelog, status=self.report.status, stop=self.request_stop,
                act=self._act, reconfigurable=self._reconfigurable)
            check_ports_free(self.cfg.network)  # a used port: one line, before any ring exists
            self.ring = create_ring(self.cfg, self.rig)
            # Tells the broker at once when a worker process dies (its pairs are lost).
            self.broker = BrokerLink(open_socket(self.ctx, SocketSpec(
                zmq.PUSH, self.endpoints.orders, sndhwm=100)), self.order_key)
            self.stats_sub = open_socket(self.ctx, SocketSpec(
                zmq.SUB, self.endpoints.tap, subscribe=(tap_msgs.TOPIC_STATS,), rcvhwm=4))
            self._install_signals()
            self.boot()
            self.report.starting(len(self.children))
            self._wait_started()  # every consumer is ready before the first pair exists
            if self.cfg.viewer.enabled and (url := self.core.node("viewer").reason):
                # Its address with its token, on this console only (the node's state, and so
                # the log and status, say where the token is, never the token).
                self.report.notice(f"viewer: {console_address(url, self.viewer_token)}")
            self._spawn(self._child("capture"), time.monotonic())
            self.started = True
            if self.latest:
                link_latest(self.run_dir)
            self._wait_started()
            self.notifier.ready(f"running in {self.run_dir}")
            self._supervise()
        finally:
            self._end(lock)
        return self.exit_code

    def _end(self, lock: IO[str]) -> None:
        """Stop every node, judge and total the run, and leave nothing of it behind."""
        if not self.window_ended:  # between windows the service goes on (waits up)
            self.notifier.stopping()
        if self.children:
            self._stop_all()
            self._judge()
            self.report.print_totals()
        if self.run_log is not None:  # its thread's socket is in the context: first
            self.run_log.stop()
        self.ctx.destroy(linger=0)
        if self.ring is not None:
            self.ring.close()  # unlinks the segment: nothing left in /dev/shm
        if not any(c.alive() for c in self.children):
            forkserver.stop()  # the nodes' server: it would leave with us, now instead
            clear_run_dir(self.run_dir)  # sockets and lock: nothing runs here any more
        lock.close()

    def _install_signals(self) -> None:
        def _stop(signo: int, _frame: Any) -> None:
            if not self.stop_requested:
                log.info("received %s, stopping", signal.Signals(signo).name)
                self.planned_stop = True
            self.stop_requested = True

        signal.signal(signal.SIGINT, _stop)
        signal.signal(signal.SIGTERM, _stop)

    def _wait_started(self) -> None:
        """Every node must report active (or, for a finished source, finalized) in time."""
        while not self.stop_requested:
            self._poll(0.05)
            now = time.monotonic()
            started = [c for c in self.children if c.proc is not None]
            for c in started:
                node = self.core.node(c.name)
                if not c.alive() and node.running:
                    if c.spec.role == "capture" and c.proc.exitcode == 0:
                        self.core.finish(c.name)  # a tiny finite source may end during start-up
                        continue
                    if c.spec.role == "worker" and c.proc.exitcode in RECYCLE_EXITS:
                        # Its first pairs already reached a limit: replaced, not a failure.
                        self._act(self.core.exited(c.name, c.proc.exitcode, now), now)
                        continue
                    self._poll(0.2)  # the dying node's last heartbeat carries its reason
                    raise died_at_start(c.name, c.proc.exitcode, node.reason)
            problem = self.core.start_problem([c.name for c in started], now)
            if problem is not None:
                raise StartupError(problem)
            if self.core.started(c.name for c in started):
                log.info("%d nodes active", len(started))
                return

    def _supervise(self) -> None:
        # --duration counts from the first pair (capture beats at once when it sends it).
        clock = DurationClock(self.duration or None, time.monotonic())
        next_status = time.monotonic() + 1.0
        next_ladder = time.monotonic()
        drain_until: float | None = None
        while not self.stop_requested:
            self._poll(0.1)
            now = time.monotonic()
            self._watch(now)
            if self.sensors is not None and now >= next_ladder:
                next_ladder = now + self.cfg.ladder.interval_s
                self._act(self.core.pools.degrade(
                    self.sensors.read(self.stats, self._outbox()), now), now)
            if clock.due(now, self.ledger_model.capture().produced):
                log.info("duration of %g s reached", self.duration)
                self.planned_stop = True
                break
            if self.window is not None and self.window.due(now, time.time()):
                log.info("the recording window ends")  # wall time decides windows only
                self.planned_stop = self.window_ended = True
                break
            if self.core.node("capture").finished and drain_until is None:
                log.info("source exhausted; draining the pools")
                drain_until = now + max(p.timeout_s for p in self.cfg.pools.values()) + 2
            if drain_until is not None and (self.ledger_model.drained() or now > drain_until):
                self.planned_stop = True
                break
            if now >= next_status:
                next_status = now + 1.0
                self._watch_clock(now)
                self.report.read_results()
                self.cpu.sample((c.spec.pool or c.spec.role, c.proc.pid if c.proc else None)
                                for c in self.children)
                self.report.status_line()
                self._notify_systemd()
                self.broker.reconcile(self.core.pools, self.stats)

    def _watch_clock(self, now: float) -> None:
        """A wall-clock step: said once, and kept in the run's timeline (ledger.json)."""
        step = self.clock_steps.observe(time.time(), now)
        if step is not None:
            log.warning("the wall clock stepped by %+.1f s: timestamps from here on are on "
                        "the new clock (durations and time-outs are not affected)", step)
            self.core.clock_stepped(now, step)

    def _outbox(self) -> int | None:
        """Records waiting for the modem, as the modem node last counted (None: no modem)."""
        modem = next((c for c in self.children if c.spec.role == "modem"), None)
        return modem.counters.get("backlog") if modem is not None else None

    def _notify_systemd(self) -> None:
        """Once a second under systemd: the watchdog's keep-alive and the status line."""
        if self.notifier.enabled:
            self.notifier.notify(**({"WATCHDOG": 1} if self.notifier.watchdog_s else {}),
                                 STATUS=self.report.status_text())

    def _child(self, role: str) -> Child:
        return next(c for c in self.children if c.spec.role == role)

    def _named(self, name: str) -> Child:
        return next(c for c in self.children if c.name == name)

    # --- watching ----------------------------------------------------------------------

    def _poll(self, timeout_s: float) -> None:
        poller = zmq.Poller()
        for s in (self.hb, self.control.sock, self.stats_sub):
            poller.register(s, zmq.POLLIN)
        events = dict(poller.poll(int(timeout_s * 1000)))
        if self.hb in events:
            while True:
                try:
                    data = self.hb.recv(zmq.NOBLOCK)
                except zmq.Again:
                    break
                self._on_heartbeat(data)
        if self.stats_sub in events:
            while True:
                try:
                    msg = tap_msgs.decode_tap(self.stats_sub.recv_multipart(zmq.NOBLOCK))
                except zmq.Again:
                    break
                except ProtocolError as exc:
                    self.ratelog.warning("stats", "bad stats message: %s", wire(str(exc)))
                    continue
                if isinstance(msg, tap_msgs.TapStats):
                    self.ledger_model.on_stats(msg.stats, time.monotonic())
        if self.control.sock in events:
            self.control.on_request(self.control.sock.recv())

    def report_snapshot(self) -> Snapshot:
        """What the report reads of this run now."""
        return Snapshot(
            nodes=[NodeView(c.name, c.proc.pid if c.proc else None, c.spec.pool or "",
                            c.counters) for c in self.children],
            stats=self.stats, planned_stop=self.planned_stop, rig=self.rig,
            rig_origin=self.rig_origin, source_where=self.source_where, ring=self.ring,
            cpu_s=self.cpu.totals())

    @property
    def stats(self) -> messages.Stats | None:
        """The run's totals over every broker so far."""
        return self.ledger_model.stats

    def capture_counts(self) -> dict[str, int]:
        """Capture's counters over the whole run, across its restarts."""
        return self.ledger_model.capture_counts()

    def _on_heartbeat(self, data: bytes) -> None:
        try:
            hb = messages.decode_heartbeat(data)
        except ProtocolError as exc:
            self.ratelog.warning("heartbeat", "dropped malformed heartbeat: %s", wire(str(exc)))
            return
        if not self.core.heartbeat(hb.node, hb.pid, hb.state, hb.reason, time.monotonic()):
            return
        c = self._named(hb.node)
        c.counters = hb.counters
        if c.spec.role == "capture":
            self.ledger_model.on_capture(messages.CaptureCounters.from_counters(hb.counters))
        elif c.spec.role == "normalizer":
            self.ledger_model.on_normalizer(hb.counters)

    def _watch(self, now: float) -> None:
        """Processes into events (exits, time), the core's actions into effects."""
        for c in self.children:
            if c.proc is not None and not c.alive() and self.core.node(c.name).running:
                actions = self.core.exited(c.name, c.proc.exitcode, now)
                node = self.core.node(c.name)
                if node.restart_at is not None:
                    log.warning("%s %s", c.name, node.reason)
                self._act(actions, now)
        self._act(self.core.tick(now), now)

    def _act(self, actions: Sequence[Action], now: float) -> None:
        for a in actions:
            if isinstance(a, Spawn):
                c = self._named(a.name)
                if a.recycled:  # planned: its pool's max_rss_mb or max_jobs
                    log.info("replacing %s, recycled (%s)", c.name, a.recycled)
                elif a.restart == 0:  # a pool grew (trapflow pool, the viewer): no restart
                    log.info("starting %s", c.name)
                else:
                    log.warning("restarting %s (restart %d)", c.name, a.restart)
                self._respawn(c, now)
            elif isinstance(a, Kill):
                log.error("%s %s; killing it", a.name, a.reason)
                c = self._named(a.name)
                if c.alive():
                    c.proc.kill()
            elif isinstance(a, WorkerGone):
                c = self._named(a.name)
                self._tell_broker_gone(c, messages.recycled_reason(a.recycled) if a.recycled
                                       else a.reason)
            elif isinstance(a, GiveUp):
                log.error("%s: %s", a.name, a.reason)
            elif isinstance(a, Retry):
                log.warning("%s: %s", a.name, a.reason)
            elif isinstance(a, Stop):
                log.info("stopping: %s", a.reason)
                self.stop_requested = True
            elif isinstance(a, AddWorker):
                self._add_worker(a)
            elif isinstance(a, Retire):
                log.info("retiring %s: %s", a.name, a.reason)
                c = self._named(a.name)
                if c.alive():
                    c.proc.terminate()  # finishes its pair, says goodbye to the broker
            elif isinstance(a, SwitchPool):
                self._switch_pool(a.pool, a.active, a.policy, a.params, a.min_interval_s)
            elif isinstance(a, LevelChanged):
                log.info("ladder: level %s (%s)", a.level, a.reason)
                self.broker.level(self.core.pools)
            elif isinstance(a, Reconfigure):
                self._reconfigure(a)
            else:
                unreachable(a)

    def _respawn(self, c: Child, now: float) -> None:
        """A restart: what the dead process had counted is kept, then a new one starts."""
        spec = c.spec
        if spec.role == "broker":
            self.ledger_model.retire_broker()
            # Pools as runtime control left them (policies); activity is reconciled by
            # BrokerLink.reconcile once its first stats arrive.
            spec = replace(spec, cfg=self.cfg)
        if spec.role == "capture":
            # Numbering goes on past any pair the dead capture may have sent after its last
            # heartbeat: a pool sees a gap, never a repeated seq.
            rate = max(self.cfg.source.rate_hz, 1.0)
            margin = int(rate * (self.cfg.supervisor.heartbeat_interval_s + 1.0)) \
                + SEQ_RESTART_GAP
            spec = replace(spec, first_seq=self.ledger_model.retire_capture(margin))
        c.spec = replace(spec, restarted=True)
        self._spawn(c, now)

    def _pool_cfg(self, pool: str, **changes: Any) -> Config:
        """The run's config with one pool's fields changed (new workers start with it)."""
        pools = dict(self.cfg.pools)
        pools[pool] = msgspec.structs.replace(pools[pool], **changes)
        self.cfg = msgspec.structs.replace(self.cfg, pools=pools)
        return self.cfg

    def _add_worker(self, a: AddWorker) -> None:
        """A pool grew: a new child (or a retired one's slot again), spawned by the Spawn
        that follows."""
        self.cfg = self._pool_cfg(a.pool, count=max(self.cfg.pools[a.pool].count, a.index + 1))
        spec = NodeSpec("worker", a.name, self.cfg, self.run_dir, pool=a.pool, index=a.index,
                        rig=self.rig, tag_size_m=self.tag_size_m,
                        ring=self.ring.name if self.ring is not None else "")
        for c in self.children:
            if c.name == a.name:
                c.spec = spec
                return
        self.children.append(Child(spec))

    def _switch_pool(self, pool: str, active: bool | None, policy: str | None,
                     params: Mapping[str, Any] | None = None,
                     min_interval_s: float | None = None) -> None:
        if policy is not None:
            self._pool_cfg(pool, policy=policy)
        self.broker.switch_pool(pool, active, policy, params, min_interval_s)

    def _reconfigure(self, a: Reconfigure) -> None:
        """New parameters: the worker restarts with them (its exit is respawned at once)."""
        self._pool_cfg(a.pool, params=dict(a.params))
        c = self._named(a.name)
        c.spec = replace(c.spec, cfg=self.cfg)
        if a.restart and c.alive() and self.core.node(a.name).reconfiguring:
            c.proc.terminate()

    def _reconfigurable(self, pool: str) -> bool:
        """Whether the pool's plugin takes new parameters in place (its class says so)."""
        try:
            return bool(registry.resolve(self.cfg.plugin_of(pool)).reconfigurable)
        except Exception as exc:  # noqa: BLE001 - the workers report a plugin that cannot load
            log.warning("pool %s: cannot tell whether its plugin reconfigures in place (%s); "
                        "restarting its workers instead", pool, exc)
            return False

    def _tell_broker_gone(self, c: Child, reason: str) -> None:
        self.broker.gone(identity.worker_identity(c.spec.pool, c.spec.index, c.proc.pid), reason)

    # --- control and the verdict ---------------------------------------------------------

    def request_stop(self) -> None:
        """A stop request (control socket): planned unless a stop was already under way."""
        self.planned_stop = self.planned_stop or not self.stop_requested
        self.stop_requested = True

    def _judge(self) -> None:
        """Exit status 1 with one line when the source could not go on or a pool failed
        every pair it was given (a run that produced nothing useful never exits 0)."""
        if not self.children:  # stopped before boot: the error raised says it all
            return
        capture = self.core.node("capture")
        problems = run_ledger.verdict(
            self.cfg.source.kind, self.capture_counts(),
            capture.reason if self.ledger_model.capture().source_gave_up else None,
            capture.finished, self.stats)
        if self.failure:
            problems.insert(0, self.failure)
        if problems:
            self.exit_code = EXIT_FAILURE
            self.failure = "; ".join(problems)
            log.error("run failed: %s", self.failure)

    # --- stopping -------------------------------------------------------------------------

    def _stop_all(self) -> None:
        """The stop ladder: ask (SIGTERM) by role in order, wait, kill what is left, join."""
        self.core.stop("stop ladder")
        if self.planned_stop:
            self.ledger_model.stopping()  # pairs on their way from here are not lost
            self.broker.stopping()  # workers leave from now on
        timeout = self.cfg.supervisor.stop_timeout_s
        for role in STOP_ORDER:
            group = [c for c in self.children if c.spec.role == role and c.alive()]
            for c in group:
                c.proc.terminate()
            deadline = time.monotonic() + (timeout if role != "capture" else timeout / 2)
            for c in group:
                c.proc.join(max(0.0, deadline - time.monotonic()))
                if c.proc.is_alive():
                    log.warning("%s did not stop in time; killing it", c.name)
                    c.proc.kill()
                    c.proc.join(1.0)
            if group:  # take the last heartbeats (final counters) and the broker's totals
                self._poll(0.3 if role == "broker" else 0.05)
        for c in self.children:
            if c.proc is not None and c.proc.is_alive():
                c.proc.kill()
                c.proc.join(1.0)
