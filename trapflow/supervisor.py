"""The supervisor (`trapflow start`): boots the process graph, watches it, restarts, stops.

Owns a PULL of heartbeats from every node, a REP control socket (status, stop)
and a SUB of the broker's stats for the status line. The whole graph is in boot().
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
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import IO, Any

import msgspec
import zmq

from trapflow import messages, registry, rig, run_totals
from trapflow.camera import StereoRig
from trapflow.config import Config
from trapflow.errors import EXIT_FAILURE, EXIT_OK, ProtocolError, StartupError, TrapflowError
from trapflow.frame_ring import FrameRing, cleanup_stale, ring_slots, slot_capacity
from trapflow.node import ACTIVE, FINALIZED, INACTIVE, NodeSpec, node_main
from trapflow.ratelog import RateLimitedLog, wire
from trapflow.transport import Endpoints, SocketSpec, new_context, open_socket

log = logging.getLogger(__name__)

# How long every node has to report its first state before start-up is declared failed.
STARTUP_TIMEOUT_S = 60.0
# Stop ladder: capture first (no new pairs), then workers and broker, the normalizer last.
STOP_ORDER = ("viewer", "capture", "worker", "events", "broker", "normalizer", "modem")
# Summed over capture restarts, with every failed_<kind> (pairs skipped at capture).
CAPTURE_TOTALS = ("produced", "dropped", "failed", "source_errors")
FAILED_PREFIX = run_totals.FAILED_PREFIX
SEQ_RESTART_GAP = 100  # extra seqs skipped at a capture restart, beyond the heartbeat lag
LOCK_FILE = "supervisor.lock"
# Roles the pipeline goes on without once their restart budget is spent; any other is
# essential and stops the run. A viewer that keeps crashing must never stop the trap.
NON_ESSENTIAL = ("worker", "viewer")


@dataclass
class Child:
    """One supervised process and what the supervisor knows about it."""

    spec: NodeSpec
    liveness_s: float
    proc: Any = None  # multiprocessing.Process
    state: str = "unconfigured"
    reason: str = ""
    last_beat: float = 0.0
    started: float = 0.0
    counters: dict[str, int] = field(default_factory=dict)
    restarts: deque[float] = field(default_factory=deque)
    restart_total: int = 0
    restart_at: float | None = None
    gave_up: bool = False
    finished: bool = False

    @property
    def name(self) -> str:
        return self.spec.name

    def alive(self) -> bool:
        return self.proc is not None and self.proc.is_alive()


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
        self.stop_requested = False
        self.exit_code = EXIT_OK
        self.failure: str | None = None  # one line: why the run failed (exit status 1)
        self.stats: messages.Stats | None = None  # the run's totals, all brokers
        self._broker_stats: messages.Stats | None = None  # the live broker's own
        self._retired: messages.Stats | None = None  # what brokers that died had counted
        self._capture_base: dict[str, int] = {}  # what captures that died had counted
        self.t0 = time.monotonic()
        self.rig: StereoRig | None = None  # decided at preflight (trapflow.rig)
        self.rig_origin = ""
        self.ring: FrameRing | None = None

    # --- the process graph --------------------------------------------------------------

    def boot(self) -> None:
        """Consumers first so nothing sent is lost: normalizer, broker, workers; capture is
        spawned once they are all active (see run())."""
        sup, cfg, run = self.cfg.supervisor, self.cfg, self.run_dir
        if self.rig is not None:
            log.info("rig from %s: %s", self.rig_origin, self.rig.describe())
        self._add(NodeSpec("normalizer", "normalizer", cfg, run), sup.liveness_s)
        if cfg.modem.enabled:
            self._add(NodeSpec("modem", "modem", cfg, run), sup.liveness_s)
        self._add(NodeSpec("broker", "broker", cfg, run), sup.liveness_s)
        if cfg.events.enabled:
            self._add(NodeSpec("events", "events", cfg, run), sup.liveness_s)
        for pool, pcfg in cfg.pools.items():
            for i in range(pcfg.count):
                spec = NodeSpec("worker", f"worker:{pool}:{i}", cfg, run, pool=pool, index=i,
                                rig=self.rig)
                self._add(spec, max(sup.liveness_s, pcfg.timeout_s))
        self._add(NodeSpec("capture", "capture", cfg, run, rig=self.rig), sup.liveness_s)
        if cfg.viewer.enabled:  # reads the taps and the control socket like `trapflow view`
            self._add(NodeSpec("viewer", "viewer", cfg, run), sup.liveness_s)
        for child in self.children:
            if child.spec.role != "capture":
                self._spawn(child)

    def _add(self, spec: NodeSpec, liveness_s: float) -> None:
        self.children.append(Child(spec, liveness_s))

    def _spawn(self, child: Child) -> None:
        if self.ring is not None:
            child.spec.extra["ring"] = self.ring.name
        # A restarted broker frees the ring slots its predecessor held; a first one must not
        # (capture's first pairs may already hold slots on their way to it).
        child.spec.extra["restarted"] = child.restart_total > 0
        child.proc = self.mp.Process(
            target=node_main, args=(child.spec, self.log_queue, os.getpid()),
            name=child.name, daemon=False,
        )
        child.proc.start()
        now = time.monotonic()
        child.started = child.last_beat = now
        child.state, child.reason, child.restart_at = "unconfigured", "", None

    # --- main loop ---------------------------------------------------------------------

    def run(self) -> int:
        """Start, supervise until stopped, stop; return the exit status."""
        self.run_dir.mkdir(parents=True, exist_ok=True)
        lock = self._lock_run_dir()
        self._preflight()
        self.endpoints = Endpoints.for_run(self.cfg.network, self.run_dir)
        self.ring = self._create_ring()
        self.ctx = new_context()
        self._start_logging()
        try:
            self.hb = open_socket(self.ctx, SocketSpec(zmq.PULL, self.endpoints.heartbeat,
                                                       bind=True))
            self.control = open_socket(self.ctx, SocketSpec(zmq.REP, self.endpoints.control,
                                                            bind=True))
            # Tells the broker at once when a worker process dies (its pairs are lost).
            self.to_broker = open_socket(self.ctx, SocketSpec(
                zmq.DEALER, self.endpoints.workers, identity=b"supervisor", sndhwm=100))
            self.stats_sub = open_socket(self.ctx, SocketSpec(
                zmq.SUB, self.endpoints.tap, subscribe=(messages.TOPIC_STATS,), rcvhwm=4))
            self._install_signals()
            self.boot()
            self._wait_started()  # every consumer is ready before the first pair exists
            self._spawn(self._child("capture"))
            self._wait_started()
            self._supervise()
        finally:
            self._stop_all()
            self._judge()
            self._print_totals()
            self.ctx.destroy(linger=0)
            self._stop_logging()
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
        self.rig, self.rig_origin = found.rig, found.origin
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
        pools = [p for p in c.pools.values() if p.count > 0 and not p.remote]
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
            self.stop_requested = True

        signal.signal(signal.SIGINT, _stop)
        signal.signal(signal.SIGTERM, _stop)

    def _wait_started(self) -> None:
        """Every node must report active (or, for a finished source, finalized) in time."""
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while not self.stop_requested:
            self._poll(0.05)
            started = [c for c in self.children if c.proc is not None]
            for c in started:
                if c.state == INACTIVE and c.reason:
                    raise StartupError(f"{c.name} cannot start: {c.reason}")
                if not c.alive():
                    if c.spec.role == "capture" and c.proc.exitcode == 0:
                        c.finished = True  # a tiny finite source may end during start-up
                        continue
                    self._poll(0.2)  # the dying node's last heartbeat carries its reason
                    why = c.reason or f"exited with status {c.proc.exitcode}"
                    raise StartupError(f"{c.name} cannot start: {why}")
            if all(c.state in (ACTIVE, FINALIZED) for c in started):
                log.info("%d nodes active", len(started))
                return
            if time.monotonic() > deadline:
                slow = [c.name for c in started if c.state != ACTIVE]
                raise StartupError(f"nodes not active after {STARTUP_TIMEOUT_S:g} s: {slow}")

    def _supervise(self) -> None:
        end = self.t0 + self.duration if self.duration else None
        next_status = time.monotonic() + 1.0
        drain_until: float | None = None
        while not self.stop_requested:
            self._poll(0.1)
            now = time.monotonic()
            self._watch(now)
            if end is not None and now >= end:
                log.info("duration of %g s reached", self.duration)
                break
            capture = self._child("capture")
            if capture.finished and drain_until is None:
                log.info("source exhausted; draining the pools")
                drain_until = now + max(p.timeout_s for p in self.cfg.pools.values()) + 2
            if drain_until is not None and (self._drained() or now > drain_until):
                break
            if now >= next_status:
                next_status = now + 1.0
                self._status_line()

    def _drained(self) -> bool:
        """Every pair capture produced reached the broker and left every pool."""
        s = self.stats
        produced = self.capture_counts()["produced"] if self._child("capture").counters else -1
        return (s is not None and s.pairs_in >= produced
                and all(p.pending == 0 and p.in_flight == 0 for p in s.pools.values()))

    def _child(self, role: str) -> Child:
        return next(c for c in self.children if c.spec.role == role)

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
                    _topic, data = self.stats_sub.recv_multipart(zmq.NOBLOCK)
                    self._on_stats(messages.decode_stats(data))
                except zmq.Again:
                    break
                except (ValueError, ProtocolError) as exc:
                    self.ratelog.warning("stats", "bad stats message: %s", wire(str(exc)))
        if self.control in events:
            self._on_control(self.control.recv())

    def _on_stats(self, stats: messages.Stats) -> None:
        self._broker_stats = stats
        self.stats = run_totals.combine(self._retired, stats)

    def _retire_capture(self, c: Child) -> None:
        """A restarted capture goes on counting, and numbering pairs past any its predecessor
        may have sent after its last heartbeat: a pool sees a gap, never a repeated seq."""
        for key, n in c.counters.items():
            if key in CAPTURE_TOTALS or key.startswith(FAILED_PREFIX):
                self._capture_base[key] = self._capture_base.get(key, 0) + n
        rate = max(self.cfg.source.rate_hz, 1.0)
        margin = int(rate * (self.cfg.supervisor.heartbeat_interval_s + 1.0)) + SEQ_RESTART_GAP
        c.spec.extra["first_seq"] = c.counters.get("next_seq", 0) + margin
        c.counters = {}

    def capture_counts(self) -> dict[str, int]:
        """Capture's counters over the whole run, across its restarts."""
        cur = next((c.counters for c in self.children if c.spec.role == "capture"), {})
        keys = {*CAPTURE_TOTALS, *(k for k in (*self._capture_base, *cur)
                                   if k.startswith(FAILED_PREFIX))}
        return {k: self._capture_base.get(k, 0) + cur.get(k, 0) for k in sorted(keys)}

    def _retire_broker(self) -> None:
        """A restarted broker counts from zero: the run's totals keep what its predecessor saw."""
        if self._broker_stats is not None:
            self._retired = run_totals.combine(self._retired,
                                               run_totals.retire(self._broker_stats))
            self._broker_stats = None

    def _on_heartbeat(self, data: bytes) -> None:
        try:
            hb = messages.decode_heartbeat(data)
        except ProtocolError as exc:
            self.ratelog.warning("heartbeat", "dropped malformed heartbeat: %s", wire(str(exc)))
            return
        for c in self.children:
            if c.name == hb.node and c.proc is not None and c.proc.pid == hb.pid:
                c.last_beat = time.monotonic()
                c.state, c.reason, c.counters = hb.state, hb.reason, hb.counters
                return

    def _watch(self, now: float) -> None:
        sup = self.cfg.supervisor
        for c in self.children:
            if c.gave_up or c.finished:
                continue
            if c.restart_at is not None:
                if now >= c.restart_at:
                    log.warning("restarting %s (restart %d)", c.name, c.restart_total)
                    if c.spec.role == "broker":
                        self._retire_broker()
                    if c.spec.role == "capture":
                        self._retire_capture(c)
                    self._spawn(c)
                continue
            if c.alive():
                # A node still configuring (loading a model, building a world) gets start-up time.
                limit = c.liveness_s if c.state != "unconfigured" else STARTUP_TIMEOUT_S
                if now - c.last_beat > limit:
                    log.error("%s silent for %.1f s; killing it", c.name, now - c.last_beat)
                    c.proc.kill()
                continue
            code = c.proc.exitcode
            if code == 0 and c.spec.role == "capture" and c.state == FINALIZED:
                c.finished = True
                continue
            if c.spec.role == "worker":
                self._tell_broker_gone(c, f"process exited with status {code}")
            # A crash (or an unexpected exit): restart with back-off inside a budget.
            while c.restarts and now - c.restarts[0] > sup.restart_window_s:
                c.restarts.popleft()
            if len(c.restarts) >= sup.max_restarts:
                c.gave_up = True
                c.state, c.reason = FINALIZED, (
                    f"gave up after {len(c.restarts)} restarts in {sup.restart_window_s:g} s "
                    f"(last exit status {code})")
                log.error("%s: %s", c.name, c.reason)
                if c.spec.role not in NON_ESSENTIAL:
                    log.error("%s is essential; stopping the pipeline", c.name)
                    self.exit_code = EXIT_FAILURE
                    self.failure = self.failure or f"{c.name} {c.reason}"
                    self.stop_requested = True
                continue
            c.restarts.append(now)
            c.restart_total += 1
            delay = min(sup.restart_backoff_s * 2 ** (len(c.restarts) - 1),
                        sup.restart_backoff_max_s)
            c.state, c.reason = INACTIVE, f"exited with status {code}; restart in {delay:.1f} s"
            log.warning("%s %s", c.name, c.reason)
            c.restart_at = now + delay

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
        return {
            "run_dir": str(self.run_dir),
            "uptime_s": round(now - self.t0, 1),
            "nodes": [
                {"name": c.name, "pid": c.proc.pid if c.proc else None, "state": c.state,
                 "reason": c.reason, "restarts": c.restart_total,
                 "last_beat_s": round(now - c.last_beat, 1), "counters": c.counters}
                for c in self.children
            ],
            "stats": _full_stats(self.stats) if self.stats else None,
            "rig": ({"calib": self.rig.id, "origin": self.rig_origin,
                     **msgspec.structs.asdict(self.rig)} if self.rig is not None else None),
            "ledger": self.ledger(),
            "ring": ({"segment": self.ring.name, "slots": self.ring.slots, **self.ring.counts()}
                     if self.ring is not None else None),
        }

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
            self.stop_requested = True
            self.control.send(msgspec.json.encode({"stopping": True}))
        else:
            self.control.send(msgspec.json.encode(self.status()))

    def _pool_restarts(self, pool: str) -> int:
        return sum(c.restart_total for c in self.children if c.spec.pool == pool)

    def status_text(self) -> str:
        """One line: time, pairs/s in, per pool processed/s, dropped, restarts."""
        up = time.monotonic() - self.t0
        s = self.stats
        if s is None:
            return f"{up:6.1f}s | waiting for stats"
        cap = self.capture_counts()
        parts = [f"{up:6.1f}s | in {s.rate_in:5.1f}/s ({s.pairs_in})"]
        if cap["dropped"]:
            parts[0] += f" capture-drop {cap['dropped']}"
        if cap["failed"]:
            parts[0] += f" capture-fail {cap['failed']}"
        for name, p in s.pools.items():
            parts.append(
                f"{name} {p.workers}w {p.rate:5.1f}/s drop {p.dropped} "
                f"err {p.errors} lost {p.lost} rst {self._pool_restarts(name)}"
            )
        return " | ".join(parts)

    def _status_line(self) -> None:
        line = self.status_text()
        if self.out.isatty():
            self.out.write("\r\x1b[K" + line)
        else:
            self.out.write(line + "\n")
        self.out.flush()

    def ledger(self) -> dict[str, Any]:
        """Where every pair went: capture's count, then per pool exactly one state each."""
        cap = self.capture_counts()
        s = self.stats
        produced = cap.get("produced", 0)
        out: dict[str, Any] = {
            "produced": produced,
            "dropped_at_capture": cap.get("dropped", 0),  # the broker was not reading
            # Read but never sent: unreadable, cut short, two sizes, too large for the ring.
            "failed_at_capture": cap.get("failed", 0),
            "capture_failures": run_totals.capture_failures(cap),
            "reached_broker": s.pairs_in if s else 0,
            "pools": {},
        }
        for name, p in (s.pools.items() if s else ()):
            out["pools"][name] = {
                "processed": p.processed, "dropped_by_policy": p.dropped,
                "policy": self.cfg.pools[name].policy, "timed_out": p.timed_out,
                "failed": p.errors, "failures": p.failures,
                # Pairs the pool never saw (lost between capture and broker) count as lost.
                "lost": p.lost + p.pending + p.in_flight + max(0, produced - p.received),
            }
        return out

    def _print_totals(self) -> None:
        if self.out.isatty():
            self.out.write("\n")
        ledger = self.ledger()
        (self.run_dir / "ledger.json").write_text(json.dumps(ledger, indent=1) + "\n")
        if self.stats is not None:
            failed = ledger["failed_at_capture"]
            kinds = ", ".join(f"{k} {v}" for k, v in ledger["capture_failures"].items())
            self.out.write(f"totals: {ledger['produced']} pairs captured, "
                           f"{ledger['reached_broker']} reached the broker"
                           f"{f', {failed} failed at capture ({kinds})' if failed else ''}\n")
            for name, p in ledger["pools"].items():
                kinds = ", ".join(f"{k} {v}" for k, v in p["failures"].items())
                self.out.write(
                    f"  {name}: processed {p['processed']}, dropped {p['dropped_by_policy']} "
                    f"({p['policy']}), timed out {p['timed_out']}, failed {p['failed']}"
                    f"{f' ({kinds})' if kinds else ''}, lost {p['lost']}, "
                    f"restarts {self._pool_restarts(name)}\n")
        self.out.write(f"results: {self.run_dir / self.cfg.normalizer.results_file}\n")
        self.out.flush()

    def _judge(self) -> None:
        """Exit status 1 with one line when the source could not go on or a pool failed
        every pair it was given (a run that produced nothing useful never exits 0)."""
        if not self.children:  # stopped before boot: the error raised says it all
            return
        capture = self._child("capture")
        problems = run_totals.verdict(
            self.cfg.source.kind, self.capture_counts(),
            capture.reason if capture.counters.get("source_gave_up") else None,
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
        self.log_queue = self.mp.Queue()
        fmt = logging.Formatter("%(asctime)s %(processName)s %(name)s %(levelname)s %(message)s")
        self.ratelog = RateLimitedLog(log)  # warnings about messages from sockets
        lcfg = self.cfg.log_file
        fileh = logging.handlers.RotatingFileHandler(
            self.run_dir / "trapflow.log", maxBytes=lcfg.max_bytes, backupCount=lcfg.backups)
        fileh.setFormatter(fmt)
        errh = logging.StreamHandler(sys.stderr)
        errh.setLevel(logging.WARNING)
        errh.setFormatter(logging.Formatter("%(levelname)s %(message)s"))
        self.listener = logging.handlers.QueueListener(
            self.log_queue, fileh, errh, respect_handler_level=True)
        root = logging.getLogger()
        root.setLevel(self.cfg.log_level)
        self._root_handlers = root.handlers[:]
        root.handlers[:] = [logging.handlers.QueueHandler(self.log_queue)]
        self.listener.start()

    def _stop_logging(self) -> None:
        self.listener.stop()
        logging.getLogger().handlers[:] = self._root_handlers
        self.log_queue.close()


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
                     run_totals.capture_failures(sup.capture_counts()))


def start(cfg: Config, run_dir: Path | None = None, duration: float | None = None,
          out: IO[str] | None = None, announce: Callable[[str], None] | None = None) -> int:
    """run(), returning only the exit status."""
    return run(cfg, run_dir, duration, out, announce).code
