"""The supervisor (`trapflow start`): boots the process graph, watches it, restarts, stops.

Owns a PULL of heartbeats from every node, a REP control socket (status, stop), the PULL
of every node's log records (trapflow.logchannel, in its own thread) and a SUB of the
broker's stats for the status line. The whole graph is in boot().
The decisions are trapflow.supervisor_state's and the counting trapflow.run_ledger's: this
shell turns processes, sockets and time into their events, and their actions into effects.
"""

from __future__ import annotations

import fcntl
import json
import logging
import logging.handlers
import multiprocessing as mp
import os
import signal
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from datetime import datetime
from pathlib import Path
from typing import IO, Any

import msgspec
import zmq

from trapflow import messages, registry, rig, run_ledger, run_summary, sdnotify
from trapflow.camera import StereoRig
from trapflow.config import Config
from trapflow.errors import EXIT_FAILURE, EXIT_OK, ProtocolError, StartupError, TrapflowError
from trapflow.frame_ring import FrameRing, cleanup_stale, ring_slots, slot_capacity
from trapflow.ladder import Ladder
from trapflow.logchannel import LogListener, PrivateRotatingFile
from trapflow.node import NodeSpec, node_main
from trapflow.ratelog import ConsoleOnce, RateLimitedLog, wire
from trapflow.run_ledger import RunLedger
from trapflow.sensors import Sensors
from trapflow.supervisor_state import (
    RECYCLE_EXITS,
    Action,
    AddWorker,
    Budget,
    DurationClock,
    GiveUp,
    Kill,
    LevelChanged,
    Lifecycle,
    NodePlan,
    Reconfigure,
    Refused,
    Retire,
    Retry,
    Spawn,
    Stop,
    SupervisorState,
    SwitchPool,
    WorkerGone,
)
from trapflow.transport import (
    Endpoints,
    SocketSpec,
    check_ports_free,
    make_private,
    new_context,
    open_socket,
)

log = logging.getLogger(__name__)

# Stop ladder: capture first (no new pairs), then workers and broker, the normalizer last.
STOP_ORDER = ("viewer", "capture", "worker", "events", "broker", "normalizer", "modem")
SEQ_RESTART_GAP = 100  # extra seqs skipped at a capture restart, beyond the heartbeat lag
# The broker's stats may predate a switch told to it this long ago (published once a second):
# only older switches are reconciled, so a change is not sent twice.
RECONCILE_AFTER_S = 2.0
LOCK_FILE = "supervisor.lock"
# results.jsonl is read incrementally for the ledger, at most this much per status tick.
RESULTS_READ_BYTES = 4 << 20
RESULTS_READS_AT_END = 10_000


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


def _full_stats(stats: messages.Stats) -> dict[str, Any]:
    """Stats as plain data with every field, zeros included (the wire form omits them)."""
    out = msgspec.structs.asdict(stats)
    out["pools"] = {n: msgspec.structs.asdict(p) for n, p in stats.pools.items()}
    return out


def default_run_dir(base: Path = Path("runs")) -> Path:
    """A fresh timestamped run directory under ./runs."""
    return base / datetime.now().strftime("%Y%m%d-%H%M%S-%f")[:-3]


def _link_latest(run_dir: Path) -> None:
    latest = run_dir.parent / "latest"
    try:
        if latest.is_symlink():
            latest.unlink()
        if not latest.exists():
            latest.symlink_to(run_dir.name)
    except OSError:
        pass  # a convenience only


class Supervisor:
    """Lifecycle manager of one pipeline."""

    def __init__(self, cfg: Config, run_dir: Path, duration: float | None = None,
                 out: IO[str] | None = None) -> None:
        self.cfg = cfg
        self.run_dir = run_dir
        self.duration = duration
        self.out = out or sys.stdout
        self.mp = mp.get_context("spawn")
        self.children: list[Child] = []
        self.core = SupervisorState((), _budget(cfg))  # the decisions (filled by boot())
        self.ledger_model = RunLedger()  # the counters (status line, status, ledger.json)
        self.stop_requested = False
        self.planned_stop = False  # a duration, stop request, signal or drained source
        self.exit_code = EXIT_OK
        self.failure: str | None = None  # one line: why the run failed (exit status 1)
        self.t0 = time.monotonic()
        self.rig: StereoRig | None = None  # decided at preflight (trapflow.rig)
        self.rig_origin = ""
        self.source_where = ""  # what the source reads (a recording's image topics)
        self.ring: FrameRing | None = None
        self.notifier = sdnotify.Notifier()  # READY/WATCHDOG/STATUS under systemd, else no-op
        self._switched_at = 0.0  # when the broker was last told of a pool switch or level
        # The degradation ladder: its decisions are the core's, its readings these sensors'.
        self.sensors: Sensors | None = None
        if cfg.ladder.enabled:
            self.core.ladder = Ladder(cfg.ladder)
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
            self._add(NodeSpec("modem", "modem", cfg, run, ring=ring), sup.liveness_s)
        self._add(NodeSpec("broker", "broker", cfg, run, ring=ring, rig=self.rig),
                  sup.liveness_s)
        if cfg.events.enabled:
            self._add(NodeSpec("events", "events", cfg, run, ring=ring), sup.liveness_s)
        for pool, pcfg in cfg.pools.items():
            if pcfg.count:  # runtime control (trapflow pool / param) knows the pools run
                self.core.add_pool(pool, pcfg.count, pcfg.policy, pcfg.params,
                                   worker_liveness(pcfg.timeout_s, sup.heartbeat_interval_s))
            for i in range(pcfg.count):
                spec = NodeSpec("worker", f"worker:{pool}:{i}", cfg, run, pool=pool, index=i,
                                rig=self.rig, ring=ring)
                self._add(spec, worker_liveness(pcfg.timeout_s, sup.heartbeat_interval_s))
        self._add(NodeSpec("capture", "capture", cfg, run, rig=self.rig, ring=ring),
                  sup.liveness_s)
        now = time.monotonic()
        if cfg.viewer.enabled:  # reads the taps and the control socket like `trapflow view`
            self._add(NodeSpec("viewer", "viewer", cfg, run), sup.liveness_s)
        for child in self.children:
            if child.spec.role != "capture":
                self._spawn(child, now)

    def _add(self, spec: NodeSpec, liveness_s: float) -> None:
        self.children.append(Child(spec))
        self.core.add(NodePlan(spec.name, spec.role, liveness_s, pool=spec.pool))

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
        lock = self._lock_run_dir()
        results = self.run_dir / self.cfg.normalizer.results_file
        if results.exists():  # a reused run directory: this run's results start at its end
            self.ledger_model.delivered.offset = results.stat().st_size
        self.ctx = new_context()
        self.listener: LogListener | None = None
        try:
            self._preflight()
            self.endpoints = Endpoints.for_run(self.cfg.network, self.run_dir)
            self._start_logging()
            self.hb = open_socket(self.ctx, SocketSpec(zmq.PULL, self.endpoints.heartbeat,
                                                       bind=True))
            self.control = open_socket(self.ctx, SocketSpec(zmq.REP, self.endpoints.control,
                                                            bind=True))
            check_ports_free(self.cfg.network)  # a used port: one line, before any ring exists
            self.ring = self._create_ring()
            # Tells the broker at once when a worker process dies (its pairs are lost).
            self.to_broker = open_socket(self.ctx, SocketSpec(
                zmq.DEALER, self.endpoints.workers, identity=b"supervisor", sndhwm=100))
            self.stats_sub = open_socket(self.ctx, SocketSpec(
                zmq.SUB, self.endpoints.tap, subscribe=(messages.TOPIC_STATS,), rcvhwm=4))
            self._install_signals()
            self.boot()
            self._wait_started()  # every consumer is ready before the first pair exists
            self._spawn(self._child("capture"), time.monotonic())
            self._wait_started()
            self.notifier.ready(f"running in {self.run_dir}")
            self._supervise()
        finally:
            self.notifier.stopping()
            if self.children:
                self._stop_all()
                self._judge()
                self._print_totals()
            self._stop_logging()  # its thread's socket is in the context: stop it first
            self.ctx.destroy(linger=0)
            if self.ring is not None:
                self.ring.close()  # unlinks the segment: nothing left in /dev/shm
            lock.close()
        return self.exit_code

    def _lock_run_dir(self) -> IO[str]:
        f = open(self.run_dir / LOCK_FILE, "a+")  # noqa: SIM115 - held while running
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.seek(0)
            other = f.read().strip() or "?"
            f.close()
            raise StartupError(
                f"run directory {self.run_dir} is in use by another trapflow (pid {other})"
            ) from None
        f.seek(0)
        f.truncate()
        f.write(str(os.getpid()))
        f.flush()
        return f

    def _preflight(self) -> None:
        """Fail before spawning anything when the source or an algorithm cannot load.

        The source, asked without being opened, also tells the rig every node uses
        (trapflow.rig: a calibration file, the source's own, its frame size, the config).
        """
        c = self.cfg
        try:
            found = rig.describe(c)
        except TrapflowError as exc:
            why = str(exc)  # source errors mostly name their kind already
            prefix = "" if why.startswith(f"{c.source.kind}:") else f"{c.source.kind}: "
            raise StartupError(f"source {prefix}{why}") from None
        self.rig, self.rig_origin, self.source_where = found.rig, found.origin, found.where
        if c.modem.enabled and c.modem.command_key:  # a bad key file: one line, nothing spawned
            from trapflow.modem.command import load_key

            load_key(c.modem.command_key)
        for pool, pcfg in self.cfg.pools.items():
            if pcfg.count > 0:
                try:
                    registry.resolve(self.cfg.plugin_of(pool))
                except TrapflowError as exc:
                    raise StartupError(f"pool {pool!r}: {exc}") from None

    def _create_ring(self) -> FrameRing | None:
        """The shared-memory frame ring every local node maps (frames.transport: shm).

        Segments of supervisors that died (kill -9, power cut) are removed first.
        """
        for name in cleanup_stale():
            log.warning("removed stale shared-memory segment %s", name)
        c = self.cfg
        if c.frames.transport != "shm":
            return None
        # A remote pool's pending pairs hold slots too (its remote workers get copies).
        pools = [p for p in c.pools.values() if p.count > 0 or p.remote]
        slots = ring_slots(pools, c.frames.preroll_slots, c.frames.spare_slots)
        # Sized from the rig: capture sends only pairs of the rig's size, so every one fits.
        w, h = self.rig.size if self.rig is not None else (c.source.width, c.source.height)
        ring = FrameRing.create(slots, slot_capacity(w, h))
        log.info("frame ring %s: %d slots of %d bytes", ring.name, slots, ring.slot_size)
        return ring

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
                    why = node.reason or f"exited with status {c.proc.exitcode}"
                    raise StartupError(f"{c.name} cannot start: {why}")
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
                self._act(self.core.degrade(self.sensors.read(self.stats, self._outbox()),
                                            now), now)
            if clock.due(now, self.ledger_model.capture().produced):
                log.info("duration of %g s reached", self.duration)
                self.planned_stop = True
                break
            if self.core.node("capture").finished and drain_until is None:
                log.info("source exhausted; draining the pools")
                drain_until = now + max(p.timeout_s for p in self.cfg.pools.values()) + 2
            if drain_until is not None and (self.ledger_model.drained() or now > drain_until):
                self.planned_stop = True
                break
            if now >= next_status:
                next_status = now + 1.0
                self._read_results()
                self._status_line()
                self._notify_systemd()
                self._reconcile_pools()

    def _outbox(self) -> int | None:
        """Records waiting for the modem, as the modem node last counted (None: no modem)."""
        modem = next((c for c in self.children if c.spec.role == "modem"), None)
        return modem.counters.get("backlog") if modem is not None else None

    def _notify_systemd(self) -> None:
        """Once a second under systemd: the watchdog's keep-alive and the status line."""
        if self.notifier.enabled:
            self.notifier.notify(**({"WATCHDOG": 1} if self.notifier.watchdog_s else {}),
                                 STATUS=self.status_text())

    def _child(self, role: str) -> Child:
        return next(c for c in self.children if c.spec.role == role)

    def _named(self, name: str) -> Child:
        return next(c for c in self.children if c.name == name)

    # --- watching ----------------------------------------------------------------------

    def _poll(self, timeout_s: float) -> None:
        poller = zmq.Poller()
        for s in (self.hb, self.control, self.stats_sub):
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
                    msg = messages.decode_tap(self.stats_sub.recv_multipart(zmq.NOBLOCK))
                except zmq.Again:
                    break
                except ProtocolError as exc:
                    self.ratelog.warning("stats", "bad stats message: %s", wire(str(exc)))
                    continue
                if isinstance(msg, messages.TapStats):
                    self.ledger_model.on_stats(msg.stats)
        if self.control in events:
            self._on_control(self.control.recv())

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

    def _read_results(self) -> None:
        """Count what results.jsonl gained since the last call (the ledger's truth)."""
        path = self.run_dir / self.cfg.normalizer.results_file
        try:
            with open(path, "rb") as f:
                f.seek(self.ledger_model.delivered.offset)
                self.ledger_model.delivered.feed(f.read(RESULTS_READ_BYTES))
        except FileNotFoundError:
            pass

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

    def _act(self, actions: list[Action], now: float) -> None:
        for a in actions:
            if isinstance(a, Spawn):
                c = self._named(a.name)
                if a.recycled:  # planned: its pool's max_rss_mb or max_jobs
                    log.info("replacing %s, recycled (%s)", c.name, a.recycled)
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
                self._tell_level()
            elif isinstance(a, Reconfigure):
                self._reconfigure(a)

    def _respawn(self, c: Child, now: float) -> None:
        """A restart: what the dead process had counted is kept, then a new one starts."""
        spec = c.spec
        if spec.role == "broker":
            self.ledger_model.retire_broker()
            # Pools as runtime control left them (policies); activity is reconciled by
            # _reconcile_pools once its first stats arrive.
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
                        rig=self.rig, ring=self.ring.name if self.ring is not None else "")
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
        self._switched_at = time.monotonic()
        try:
            self.to_broker.send(messages.encode(messages.PoolSwitch(
                pool=pool, active=active, policy=policy,
                params=dict(params) if params is not None else None,
                min_interval_s=min_interval_s)), zmq.NOBLOCK)
        except zmq.Again:
            log.warning("could not tell the broker about pool %s now; status reconciles it",
                        pool)

    def _tell_level(self) -> None:
        """The ladder's level to the broker, which publishes it in its stats (status, the
        viewer, and the modem node, which sends a health record when it changes)."""
        view = self.core.ladder_view()
        if view is None:
            return
        self._switched_at = time.monotonic()
        try:
            self.to_broker.send(messages.encode(messages.LadderLevel(
                level=view["level"], reason=view["reason"][:256])), zmq.NOBLOCK)
        except zmq.Again:
            log.warning("could not tell the broker the ladder's level now; status reconciles it")

    def _reconcile_pools(self) -> None:
        """A restarted broker starts every pool active, with no minimum interval and no
        level: tell it again what runtime control and the ladder decided."""
        stats = self.stats
        if time.monotonic() - self._switched_at < RECONCILE_AFTER_S:
            return  # its stats may not show the latest switch yet
        for name, p in self.core.pools.items():
            seen = stats.pools.get(name) if stats is not None else None
            want = p.state == Lifecycle.ACTIVE
            if seen is not None and seen.active != want:
                self._switch_pool(name, want, None)
            if seen is not None and seen.min_interval_s != p.min_interval_s:
                self._switch_pool(name, None, None, min_interval_s=p.min_interval_s)
        view = self.core.ladder_view()
        if stats is not None and view is not None and stats.level != view["level"]:
            self._tell_level()

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
        ident = messages.worker_identity(c.spec.pool, c.spec.index, c.proc.pid)
        try:
            self.to_broker.send(messages.encode(messages.Gone(worker=ident, reason=reason)),
                                zmq.NOBLOCK)
        except zmq.Again:
            pass  # the broker's own timeout will evict it

    # --- control and status --------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        """Everything `trapflow status` shows, as JSON-able builtins."""
        now = time.monotonic()
        nodes = []
        for c in self.children:
            n = self.core.node(c.name)
            nodes.append({"name": c.name, "pid": c.proc.pid if c.proc else None,
                          "state": str(n.state), "reason": n.reason,
                          "restarts": n.restart_total, "recycled": n.recycled,
                          "gave_up": n.gave_up,
                          "retries": n.retried, "last_beat_s": round(now - n.last_beat, 1),
                          "counters": c.counters})
        return {
            "run_dir": str(self.run_dir),
            "uptime_s": round(now - self.t0, 1),
            "nodes": nodes,
            "stats": _full_stats(self.stats) if self.stats else None,
            "supervision": self.supervision(),
            "ledger": self.ledger(final=False),  # ledger.json so far
            "rig": ({"calib": self.rig.id, "origin": self.rig_origin,
                     **msgspec.structs.asdict(self.rig)} if self.rig is not None else None),
            "ring": ({"segment": self.ring.name, "slots": self.ring.slots, **self.ring.counts()}
                     if self.ring is not None else None),
        }

    def supervision(self) -> dict[str, Any]:
        """Give-ups, retries and recycles over the run, and their timeline (seconds since
        start); `recycled` per pool, by why (rss, jobs)."""
        counts = self.core.counts()
        return {"gave_up": counts["gave_up"], "retries": counts["retry"],
                "capped": counts["capped"], "control": counts["control"],
                "recycled": {p: dict(by) for p, by in self.core.recycled.items()},
                "pools": self.core.pool_view(), "ladder": self.core.ladder_view(),
                "timeline": [{"t_s": round(e.t - self.t0, 1), "node": e.node, "kind": e.kind,
                              "reason": e.reason} for e in self.core.timeline]}

    def _on_control(self, data: bytes) -> None:
        # A request is read whole: REP answers only after its last frame (else EFSM, exit 1).
        extra = 0
        while self.control.getsockopt(zmq.RCVMORE):
            self.control.recv()
            extra += 1
        try:
            if extra:
                raise ProtocolError(f"control request: expected 1 frame, got {extra + 1}; "
                                    f"send one encoded StatusRequest or StopRequest")
            req = messages.decode_control(data)
        except ProtocolError as exc:
            self.ratelog.warning("control", "refused a control request: %s", wire(str(exc)))
            self.control.send(msgspec.json.encode({"error": str(exc)}))
            return
        if isinstance(req, messages.StopRequest):
            self.planned_stop = self.planned_stop or not self.stop_requested
            self.stop_requested = True
            self.control.send(msgspec.json.encode({"stopping": True}))
        elif isinstance(req, (messages.PoolRequest, messages.ParamRequest)):
            self.control.send(msgspec.json.encode(self._change(req)))
        elif isinstance(req, messages.LevelRequest):
            self.control.send(msgspec.json.encode(self._force_level(req.level)))
        else:
            self.control.send(msgspec.json.encode(self.status()))

    def _change(self, req: messages.PoolRequest | messages.ParamRequest) -> dict[str, Any]:
        """A runtime change: the core decides, this applies; the reply says what changed."""
        now = time.monotonic()
        try:
            if isinstance(req, messages.ParamRequest):
                in_place = req.pool in self.core.pools and self._reconfigurable(req.pool)
                actions = self.core.set_param(req.pool, req.key, req.value, now, in_place)
            elif req.count is not None:
                actions = self.core.set_count(req.pool, req.count, now)
            elif req.policy is not None:
                actions = self.core.set_policy(req.pool, req.policy, now)
            else:
                actions = self.core.set_active(req.pool, bool(req.active), now)
        except Refused as exc:
            log.warning("refused a control change: %s", exc)
            return {"error": str(exc)}
        change = self.core.timeline[-1]
        log.info("control: %s %s", change.node, change.reason)
        self._act(actions, now)
        return {"changed": change.node, "change": change.reason,
                "pool": self.core.pool_view()[req.pool]}

    def _force_level(self, level: str) -> dict[str, Any]:
        """`trapflow level NAME|auto`: the core decides, this applies; the reply says the
        level, whether it is forced and why (or the error)."""
        now = time.monotonic()
        try:
            actions = self.core.force_level(level, now)
        except Refused as exc:
            log.warning("refused a level change: %s", wire(str(exc)))
            return {"error": str(exc)}
        if not actions:
            log.info("ladder: %s", self.core.timeline[-1].reason)
        self._act(actions, now)
        view = self.core.ladder_view()
        assert view is not None
        return {"level": view["level"], "auto": not view["forced"], "reason": view["reason"]}

    def _pool_restarts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for c in self.children:
            if c.spec.pool:
                out[c.spec.pool] = out.get(c.spec.pool, 0) + self.core.node(c.name).restart_total
        return out

    def status_text(self) -> str:
        """One line: time, pairs/s in, per pool processed/s, dropped, restarts."""
        view = self.core.ladder_view()
        level = view["level"] if view is not None and view["index"] else ""
        return self.ledger_model.status_text(time.monotonic() - self.t0, self._pool_restarts(),
                                             level=level)

    def _status_line(self) -> None:
        line = self.status_text()
        if self.out.isatty():
            self.out.write("\r\x1b[K" + line)
        else:
            self.out.write(line + "\n")
        self.out.flush()

    def ledger(self, final: bool = True) -> dict[str, Any]:
        """Where every pair went: capture's count, then per pool exactly one state each."""
        return self.ledger_model.ledger({n: p.policy for n, p in self.cfg.pools.items()},
                                        self._pool_restarts(), self.supervision(), final,
                                        planned_stop=self.planned_stop)

    def _print_totals(self) -> None:
        if self.out.isatty():
            self.out.write("\n")
        for _ in range(RESULTS_READS_AT_END):
            before = self.ledger_model.delivered.offset
            self._read_results()
            if self.ledger_model.delivered.offset == before:
                break
        ledger = self.ledger()
        (self.run_dir / "ledger.json").write_text(json.dumps(ledger, indent=1) + "\n")
        if self.stats is not None:
            self.out.write(run_ledger.totals_text(ledger))
        c = self.cfg
        self.out.write("".join(f"{line}\n" for line in run_summary.summary_lines(
            self.run_dir / c.normalizer.results_file,
            sum(self.ledger_model.delivered.counts.values()), self.run_dir / c.outbox.path,
            self.run_dir / c.events.folder if c.events.enabled else None, c.source.kind,
            self.source_where, c.outbox)))
        self.out.flush()

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
            try:  # workers leave from now on: a send to one that left is no news
                self.to_broker.send(messages.encode(messages.Stopping()), zmq.NOBLOCK)
            except zmq.Again:
                pass  # the broker is busy; a departure is then logged as a warning
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

    # --- logging -----------------------------------------------------------------------------

    def _start_logging(self) -> None:
        fmt = logging.Formatter("%(asctime)s %(processName)s %(name)s %(levelname)s %(message)s")
        self.ratelog = RateLimitedLog(log)  # warnings about messages from sockets
        lcfg = self.cfg.log_file
        logfile = self.run_dir / "trapflow.log"
        fileh = PrivateRotatingFile(logfile, maxBytes=lcfg.max_bytes,
                                    backupCount=lcfg.backups)
        fileh.setFormatter(fmt)
        errh = logging.StreamHandler(sys.stderr)
        errh.setLevel(logging.WARNING)
        errh.addFilter(ConsoleOnce())  # a warning every worker gives, said once
        errh.setFormatter(logging.Formatter("%(levelname)s %(message)s"))
        # Nodes' records arrive on the log socket; the supervisor's own go straight out.
        self.listener = LogListener(self.ctx, self.endpoints.log, [fileh, errh])
        root = logging.getLogger()
        root.setLevel(self.cfg.log_level)
        self._root_handlers = root.handlers[:]
        root.handlers[:] = [fileh, errh]
        self.listener.start()

    def _stop_logging(self) -> None:
        if self.listener is None:
            return
        self.listener.stop()
        for h in logging.getLogger().handlers:
            h.close()
        logging.getLogger().handlers[:] = self._root_handlers


@dataclass
class RunResult:
    """How a run ended: its exit status, the run's totals, and the one-line failure if any."""

    code: int
    stats: messages.Stats | None
    failure: str | None = None
    capture_failures: dict[str, int] = field(default_factory=dict)  # pairs skipped, by kind


def run(cfg: Config, run_dir: Path | None = None, duration: float | None = None,
        out: IO[str] | None = None, announce: Callable[[str], None] | None = None,
        ) -> RunResult:
    """Run a pipeline until duration, a signal, or the end of a finite source.

    Returns the exit status, the last stats the broker published (the run's totals) and,
    when the status is 1, the line that says why.
    """
    if run_dir is None:
        run_dir = default_run_dir()
        run_dir.mkdir(parents=True, exist_ok=True)
        _link_latest(run_dir)
    if announce:
        announce(f"run directory: {run_dir}")
    sup = Supervisor(cfg, run_dir, duration, out)
    code = sup.run()
    return RunResult(code, sup.stats, sup.failure,
                     run_ledger.capture_failures(sup.capture_counts()))


def start(cfg: Config, run_dir: Path | None = None, duration: float | None = None,
          out: IO[str] | None = None, announce: Callable[[str], None] | None = None) -> int:
    """run(), returning only the exit status."""
    return run(cfg, run_dir, duration, out, announce).code
