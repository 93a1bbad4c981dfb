"""The worker process: runs one algorithm plugin through its lifecycle on pairs it pulls.

Owns a DEALER to the broker (or, for a local worker of the shared-memory ring, a
local link): READY with a credit, then one job at a time per credit, each answered
by DONE (+ result) or FAILED. Bad input fails one pair, never the process.
Past its pool's max_rss_mb or max_jobs after a pair, it answers that pair, says goodbye
(GONE, reason recycled:rss or recycled:jobs) and exits with EXIT_RECYCLED_RSS or
EXIT_RECYCLED_JOBS: the supervisor replaces it at once, outside the restart budget.
"""

from __future__ import annotations

import logging
import os
import time
from typing import Any

import cv2
import msgspec
import numpy as np
import psutil
import zmq

from trapflow import registry
from trapflow.errors import ProtocolError, WorkerError
from trapflow.plugin import Context, Worker, configure_plugin
from trapflow.pools.pair_path import ViewPacer, ViewSpec, process_pair
from trapflow.runtime.lifecycle import EXIT_RECYCLED_JOBS, EXIT_RECYCLED_RSS
from trapflow.runtime.node import ACTIVE, FINALIZED, INACTIVE, Node, NodeSpec, freeze_heap
from trapflow.runtime.ratelog import RateLimitedLog
from trapflow.wire import frame_msgs, identity, messages
from trapflow.wire.frame_ring import RingError, RingReader
from trapflow.wire.links import LINK_RETRY_S, Link, LinkClient, LinkClosed
from trapflow.wire.transport import SocketSpec, open_socket

log = logging.getLogger(__name__)

# With a pool's `save: true`, one input pair and its result are kept per this interval.
SAVE_INTERVAL_S = 1.0
# A worker taking a pair beats at once unless its last heartbeat is younger than this.
TAKE_BEAT_S = 0.05
SEND_WAIT_MS = 1000  # how long a Done may wait for room in a busy broker's queue


def apply_priority(nice: int, affinity: list[int]) -> None:
    """Lower this process's CPU priority and pin it, as the pool's config says."""
    if nice:
        os.nice(nice)
    if affinity:
        usable = set(range(psutil.cpu_count() or 1))
        cores = [c for c in affinity if c in usable]
        if cores:
            psutil.Process().cpu_affinity(cores)
        else:
            log.warning("affinity %s names no core of this machine; not pinned", affinity)


class WorkerNode(Node):
    """One process of a pool."""

    def __init__(self, spec: NodeSpec) -> None:
        super().__init__(spec)
        self.pool = spec.pool
        self.pcfg = self.cfg.pools[self.pool]
        self.ident = self._identity()
        # Local workers of the ring get descriptors over a local link; others, bytes over zmq.
        self.local = bool(spec.ring) and not self.pcfg.remote
        self.link = LinkClient(self.endpoints.workers_link)
        self.dealer: zmq.Socket[bytes] | None = None
        if not self.local:
            self.dealer = self._open_dealer()
        self.plugin: Worker | None = None
        self.rig = spec.the_rig()
        # A detector's confident boxes leave with their crops while this worker holds the
        # pixels: the review queue's best views (the pair is gone from the ring by the time
        # its result reaches the normalizer).
        self.views: ViewPacer | None = None
        if self.cfg.review.enabled and self.cfg.observe.enabled:
            self.views = ViewPacer(ViewSpec(self.cfg.observe.high, self.cfg.review.crop_px))
        self.calib = self.rig.id
        self._reader: RingReader | None = None
        self._next_save = 0.0
        self.processed = 0
        self.proc_us = 0  # processing time of every processed pair, summed (for /metrics)
        self.proc_cpu_us = 0  # CPU time (all threads) inside process(), summed (for the bench)
        self.failed = 0
        self.free = self.pcfg.credit
        self._take_beat_s = min(TAKE_BEAT_S, self.pcfg.timeout_s / 20)
        self.ratelog = RateLimitedLog(log)
        self._proc = psutil.Process()
        self.recycle: tuple[int, str] | None = None  # (exit status, Gone reason) once due
        if self.pcfg.debug:
            logging.getLogger().setLevel(logging.DEBUG)

    def _identity(self) -> str:
        """The routing identity of this process (a remote worker names its host too)."""
        return identity.worker_identity(self.pool, self.spec.index, os.getpid())

    def _open_dealer(self) -> zmq.Socket[bytes]:
        """The DEALER to the broker, for workers that get the bytes (remote: true)."""
        return open_socket(
            self.ctx, SocketSpec(zmq.DEALER, self.endpoints.workers, identity=self.ident.encode()))

    def counters(self) -> dict[str, int]:
        stale = self._reader.rejected if self._reader is not None else 0
        return {"processed": self.processed, "failed": self.failed, "stale_reads": stale,
                "proc_us": self.proc_us, "proc_cpu_us": self.proc_cpu_us}

    def _ring(self) -> RingReader:
        """The shared-memory ring, mapped once, on first use."""
        if self._reader is None:
            name = self.spec.ring
            if not name:
                raise ProtocolError("job: got a frame ref, but this worker has no ring")
            self._reader = RingReader(name)
        return self._reader

    def _configure(self) -> bool:
        try:
            cls = registry.resolve(self.cfg.plugin_of(self.pool))
            plugin = cls()
            ctx = Context(
                pool=self.pool, worker=self.ident, run_dir=self.spec.run_dir,
                rig=self.rig, debug=self.pcfg.debug, save=self.pcfg.save,
                time=self.pcfg.time, tag_size_m=self.spec.tag_size_m,
            )
            configure_plugin(plugin, self.pcfg.params, ctx)
            self.set_state(INACTIVE)
            plugin.activate()
        except Exception as exc:  # noqa: BLE001 - a plugin failure: up, inactive, why
            why = str(exc) if isinstance(exc, WorkerError) else f"{type(exc).__name__}: {exc}"
            self.set_state(INACTIVE, f"cannot start algorithm: {why}")
            return False
        self.plugin = plugin
        self.calib = (plugin.rig or self.rig).id  # a plugin's own calibration wins
        self.set_state(ACTIVE)
        return True

    def run(self) -> int:
        apply_priority(self.pcfg.nice, self.pcfg.affinity)
        if not self._configure():
            while not self.stopping:  # stay visible to status with the reason; no restart loop
                self.beat()
                time.sleep(0.1)
            return 0
        freeze_heap()  # the algorithm and its model are loaded
        if self.dealer is not None:
            self._send([self._ready()])
        next_alive = 0.0
        while not self.stopping:
            frames = self._recv(100)
            if frames is not None and len(frames) == 1:  # not a job: new parameters
                self._reconfigure(frames[0])
                frames = None
            if frames is not None:
                # Taking work: the supervisor times this pair from here (its pool's timeout_s
                # bounds the process) and knows the worker active, even on its first pair.
                # Not one heartbeat per pair: encoding and sending it cost a worker about 60
                # us a pair (a third of its CPU on the raw ring path) and the supervisor a
                # decode each; a pair is timed at most TAKE_BEAT_S (or a twentieth of
                # timeout_s) early.
                self.beat(due=True, fresh_s=self._take_beat_s)
                self.free -= 1
                self._handle(frames)
                self.free += 1
                self.recycle = self._recycle_due()
                if self.recycle is not None:
                    break
            now = time.monotonic()
            if now >= next_alive:
                next_alive = now + self.cfg.supervisor.heartbeat_interval_s
                self._send([messages.Alive(worker=self.ident, pool=self.pool,
                                           free=max(self.free, 0))])
            self.beat()
        # Leaving on purpose: the broker settles this worker's jobs now, quietly. Recycled,
        # it has answered its last pair; what the broker sent after that goes to another.
        code, reason = self.recycle or (0, messages.GONE_STOPPING)
        self._send([messages.Gone(worker=self.ident, reason=reason)])
        assert self.plugin is not None
        self.plugin.deactivate()
        self.set_state(INACTIVE)
        self.plugin.cleanup()
        self.plugin.shutdown()
        self.set_state(FINALIZED, reason if self.recycle else "", normal=True)
        if self.dealer is not None:  # the goodbye must leave before the context goes
            self.dealer.close(linger=SEND_WAIT_MS)
        return code

    def _recycle_due(self) -> tuple[int, str] | None:
        """After a pair: past the pool's max_jobs or max_rss_mb, the exit status and the
        goodbye's reason; else None. Reading the RSS costs about 20 us (/proc/self/statm)."""
        jobs = self.processed + self.failed
        if self.pcfg.max_jobs and jobs >= self.pcfg.max_jobs:
            log.info("%s: recycled after %d pairs (max_jobs %d)", self.ident, jobs,
                     self.pcfg.max_jobs)
            return EXIT_RECYCLED_JOBS, messages.recycled_reason(
                "jobs", f"{jobs} pairs, max_jobs {self.pcfg.max_jobs}")
        if self.pcfg.max_rss_mb:
            rss_mb = self._proc.memory_info().rss / (1 << 20)
            if rss_mb > self.pcfg.max_rss_mb:
                log.info("%s: recycled at %.0f MiB resident (max_rss_mb %d) after %d pairs",
                         self.ident, rss_mb, self.pcfg.max_rss_mb, jobs)
                return EXIT_RECYCLED_RSS, messages.recycled_reason(
                    "rss", f"{rss_mb:.0f} MiB, max_rss_mb {self.pcfg.max_rss_mb}")
        return None

    def _reconfigure(self, frame: Any) -> None:
        """The pool's parameters changed (`trapflow param`): configure the plugin again,
        between pairs. A plugin that fails with them ends this process, and the supervisor
        starts a new one with the same parameters (it reports why, like any start)."""
        try:
            msg = messages.decode_configure(frame)
        except ProtocolError as exc:
            self.ratelog.warning("configure", "%s: dropped malformed configure: %s",
                                 self.ident, exc)
            return
        assert self.plugin is not None
        if msg.pool != self.pool or not self.plugin.reconfigurable:
            log.warning("%s: ignored new parameters for pool %s (plugin reconfigurable: %s)",
                        self.ident, msg.pool, self.plugin.reconfigurable)
            return
        self.pcfg = msgspec.structs.replace(self.pcfg, params=dict(msg.params))
        ctx = Context(pool=self.pool, worker=self.ident, run_dir=self.spec.run_dir,
                      rig=self.rig, debug=self.pcfg.debug, save=self.pcfg.save,
                      time=self.pcfg.time, tag_size_m=self.spec.tag_size_m)
        try:
            self.plugin.deactivate()
            self.set_state(INACTIVE)
            configure_plugin(self.plugin, self.pcfg.params, ctx)
            self.plugin.activate()
        except Exception as exc:  # noqa: BLE001 - bad parameters: a fresh process says why
            why = str(exc) if isinstance(exc, WorkerError) else f"{type(exc).__name__}: {exc}"
            log.error("%s: cannot apply new parameters: %s; restarting", self.ident, why)
            self.stopping = True
            return
        self.set_state(ACTIVE)
        log.info("%s: reconfigured in place with %s", self.ident, sorted(msg.params))

    def _save(self, left: np.ndarray, right: np.ndarray, result: messages.Result) -> None:
        """Debug aid (`save: true`): at most one input pair and its result per second."""
        now = time.monotonic()
        if now < self._next_save:
            return
        self._next_save = now + SAVE_INTERVAL_S
        folder = self.spec.run_dir / "debug" / self.ident.replace(":", "-")
        folder.mkdir(parents=True, exist_ok=True)
        stem = folder / f"{result.seq:08d}"
        cv2.imwrite(f"{stem}_left.jpg", left)
        cv2.imwrite(f"{stem}_right.jpg", right)
        (folder / f"{result.seq:08d}.json").write_bytes(
            msgspec.json.encode(messages.to_builtins(result)))

    def _ready(self) -> messages.Ready:
        return messages.Ready(worker=self.ident, pool=self.pool, credit=self.pcfg.credit)

    def _recv(self, timeout_ms: int) -> list[Any] | None:
        """The next job's frames, or None after timeout_ms."""
        if self.dealer is not None:
            if self.dealer.poll(timeout_ms, zmq.POLLIN):
                return self.dealer.recv_multipart(copy=False)
            return None
        link = self._link()
        if link is None:
            time.sleep(LINK_RETRY_S)
            return None
        try:  # a busy pipeline has the next job waiting: no poll call for it
            frames = link.recv()
            if frames is None and link.wait(timeout_ms):
                frames = link.recv()
            return frames
        except LinkClosed as exc:  # the broker died: a new one will listen at the same path
            log.warning("%s: %s; reconnecting", self.ident, exc)
            self.link.drop()
        except ProtocolError as exc:
            self.ratelog.warning("link", "%s: dropped malformed job: %s", self.ident, exc)
        return None

    def _link(self) -> Link | None:
        """The local link to the broker; READY goes first on every new connection."""
        if self.link.link is None and self.link.get() is not None:
            self.free = self.pcfg.credit
            self._send([self._ready()])
        return self.link.link

    def _send(self, msgs: list[Any]) -> None:
        frames = [m if isinstance(m, bytes) else messages.encode(m) for m in msgs]
        if self.dealer is not None:
            self.dealer.send_multipart(frames)
            return
        link = self.link.link
        if link is None:
            return  # no broker: the job this answers was lost with the one that died
        try:
            if not link.send(frames) and not (link.wait_writable(SEND_WAIT_MS)
                                              and link.send(frames)):
                self.ratelog.warning("busy", "%s: broker queue full; message dropped",
                                     self.ident)
        except LinkClosed as exc:
            log.warning("%s: %s; reconnecting", self.ident, exc)
            self.link.drop()
        except ProtocolError as exc:  # a result too big for one datagram fails its pair
            done = msgs[0]
            if isinstance(done, messages.Done):
                self._send([messages.Failed(worker=self.ident, pool=self.pool, seq=done.seq,
                                            reason=str(exc)[:300], kind="ProtocolError")])

    def _handle(self, frames: list[Any]) -> None:
        assert self.plugin is not None
        seq = -1
        try:
            if len(frames) not in (3, 4):
                raise ProtocolError(f"job: expected 4 frames [job, header, left, right] or 3 "
                                    f"[job, header, frame ref], got {len(frames)}")
            job = messages.decode_job(frames[0])
            ref: frame_msgs.FrameRef | None = None
            if len(frames) == 3:
                header, ref = frame_msgs.check_pair_ref(frames[1:])
                raw_left, raw_right = self._ring().view(ref)  # zero-copy views of the slot
            else:
                header = messages.check_pair_frames(frames[1:])
                raw_left, raw_right = frames[2], frames[3]
            seq = header.seq
            done = process_pair(self.plugin, header, raw_left, raw_right, pool=self.pool,
                                worker=self.ident, calib=self.calib, gap=job.gap,
                                views=None if self.views is None else self.views.due(header))
            if ref is not None:
                # The slot must still hold this pair, or the result came from other bytes.
                self._ring().check(ref)
        except Exception as exc:  # noqa: BLE001 - one bad pair fails, the worker goes on
            self.failed += 1
            reason = str(exc) if isinstance(exc, (ProtocolError, WorkerError, RingError)) else (
                f"{type(exc).__name__}: {exc}")
            self.ratelog.warning("fail", "%s: pair %d failed: %s", self.ident, seq, reason)
            self._send([messages.Failed(worker=self.ident, pool=self.pool, seq=seq,
                                        reason=reason[:300], kind=type(exc).__name__)])
            return
        result, proc_ns = done.result, done.result.proc_ns
        if self.views is not None:
            self.views.done(header, result.body)
        self.processed += 1
        self.proc_us += proc_ns // 1000
        self.proc_cpu_us += done.cpu_ns // 1000
        if self.pcfg.time:
            log.info("%s: pair %d in %.1f ms", self.ident, header.seq, proc_ns / 1e6)
        if self.pcfg.save and self.plugin.needs_images:
            self._save(done.pair.left, done.pair.right, result)
        self._send([messages.Done(worker=self.ident, pool=self.pool, seq=header.seq),
                    messages.encode(result)])
