"""The capture process: reads stereo frames from a source, encodes them once, pushes them.

Owns a PUSH to the broker (with the shared-memory ring, a local link carrying
descriptors). A live source never waits for an algorithm: when the broker is not
reading, the pair is dropped here and counted. A finite one waits instead (a replay at
rate 0 is held back by the broker until every pool has room: lossless, at the slowest
pool's pace). A pair it cannot read or place (a bad
file, an undecodable message, too large for the ring) is counted as failed, by kind,
and skipped; a finite source that fails otherwise ends the run (live ones are retried).
"""

from __future__ import annotations

import logging
import time
from typing import Any

import msgspec
import numpy as np
import zmq

from trapflow.capture.busy import Busy, Drop, Wait, when_busy
from trapflow.capture.image_watch import ImageWatch
from trapflow.errors import unreachable
from trapflow.gate.duty import DutyCycle
from trapflow.gate.motion import MotionConfig, MotionDetector
from trapflow.gate.policy import duty_config
from trapflow.runtime.node import ACTIVE, FINALIZED, INACTIVE, Node, NodeSpec
from trapflow.runtime.ratelog import RateLimitedLog
from trapflow.sources.base import Frames, SkipPair, Source, SourceError
from trapflow.sources.factory import open_source
from trapflow.sources.rig import mismatch, run_calibration
from trapflow.wire import jpeg, messages, tap_msgs
from trapflow.wire.frame_ring import RingError, RingWriter
from trapflow.wire.links import LinkClient, LinkClosed
from trapflow.wire.transport import SocketSpec, open_socket

log = logging.getLogger(__name__)

RETRY_BACKOFF_S = (0.5, 1.0, 2.0, 5.0, 10.0)
# Motion regions carried on a header, largest first: the rest are specks beside them, and
# the header stays a few hundred bytes for every pool it goes to.
MOTION_REGIONS = 16


class CaptureNode(Node):
    """Paces a source, stamps and encodes each pair, and hands it to the broker."""

    def __init__(self, spec: NodeSpec) -> None:
        super().__init__(spec)
        self.push = open_socket(
            self.ctx, SocketSpec(zmq.PUSH, self.endpoints.capture, sndhwm=4)
        )
        self.src_cfg = self.cfg.source
        self.rig = spec.the_rig()  # every pair sent must have its size
        # The calibration file, read here again (sources.rig decides which, as at preflight).
        self.source: Source = open_source(self.src_cfg, self.rig, run_calibration(self.cfg))
        # A restarted capture continues past its predecessor's numbers (the supervisor knows).
        self.seq = spec.first_seq
        self.produced = 0
        self.dropped = 0
        self.failed: dict[str, int] = {}  # pairs skipped at capture, by kind
        self.source_errors = 0  # a live source lost and reopened
        self.gave_up = 0  # 1 once a finite source failed for good (the reason is in the state)
        # With a shared-memory ring each pair is written once there; only a descriptor is sent.
        ring_name = spec.ring
        self.ring = RingWriter(ring_name) if ring_name else None
        # With the ring, descriptors go over a local link.
        self.link = LinkClient(self.endpoints.capture_link)
        self.ratelog = RateLimitedLog(log)
        # With a gated pool, the motion gate looks at every left image here, once for all
        # pools (a fraction of a millisecond on a small grey copy); its result rides on the
        # pair's header to the broker, which decides what each gated pool gets.
        gated = any(p.gate == "motion" for p in self.cfg.pools.values())
        # Duty cycling (opt-in): an idle rate after a while without motion, decided here on
        # the detector's own result, so the full rate is back for the very next pair.
        self.duty = DutyCycle(duty_config(self.cfg), self.src_cfg.rate_hz)
        self.period_ns = int(1e9 / self.src_cfg.rate_hz)
        self.next_ns = 0  # when the next pair is due (monotonic)
        self.motion = MotionDetector(MotionConfig()) if gated or self.duty.enabled else None
        # Fouling and turbidity: one left image every few seconds, its state to the broker.
        ih = self.cfg.image_health
        self.image_watch = ImageWatch(ih, spec.run_dir, self.rig.size) if ih.enabled else None
        if self.duty.enabled and not spec.restarted:
            log.info("duty cycling: %g pairs/s after %g s without motion, %g pairs/s again on "
                     "the first pair that moves (visual odometry runs at the idle rate too)",
                     self.duty.idle_hz, self.duty.cfg.idle_after_s, self.duty.full_hz)

    def capture_counters(self) -> messages.CaptureCounters:
        """What the supervisor sums over capture's restarts."""
        sync: dict[str, int] = {}
        live = getattr(self.source, "sync", None)  # live cameras paired by timestamp
        if live is not None:
            for k, v in live.stats.as_dict().items():
                key = f"sync_{k[:-3]}_us" if k.endswith("_ms") else f"sync_{k}"
                sync[key] = int(v * 1000) if k.endswith("_ms") else int(v)
        return messages.CaptureCounters(
            produced=self.produced, dropped=self.dropped, failures=dict(self.failed),
            source_errors=self.source_errors, source_gave_up=self.gave_up,
            next_seq=self.seq, sync=sync)

    def counters(self) -> dict[str, int]:
        return self.capture_counters().to_counters()

    def _open(self) -> bool:
        try:
            self.source.open()
        except SourceError as exc:
            self.set_state(INACTIVE, f"source cannot open: {exc}")
            return False
        self.set_state(ACTIVE)
        return True

    def run(self) -> int:
        attempt = 0
        while not self.stopping and not self._open():
            self._wait(RETRY_BACKOFF_S[min(attempt, len(RETRY_BACKOFF_S) - 1)])
            attempt += 1
        self.next_ns = time.monotonic_ns()
        while not self.stopping:
            if not self.source.paced:
                delay = self.next_ns - time.monotonic_ns()
                if delay > 0:
                    self._wait(delay / 1e9)
                    continue
                # Behind by more than a period (a slow frame): skip ahead, never burst.
                self.next_ns = max(self.next_ns + self.period_ns,
                                   time.monotonic_ns() - self.period_ns)
            try:
                frames = self.source.read()
            except SkipPair as exc:  # the source is past it: count, say once, go on
                self._fail(exc.kind, "skipped a pair: %s", exc)
                self.beat()
                self.next_ns = time.monotonic_ns()  # a pair never sent costs no period
                continue
            except SourceError as exc:
                if self.source.finite:  # a file or recording will not get better by waiting
                    log.error("source failed; no more pairs: %s", exc)
                    self.gave_up = 1
                    self.set_state(FINALIZED, f"source failed: {exc}")
                    self.source.close()
                    self.beat()
                    return 0
                self.source_errors += 1
                self.set_state(INACTIVE, f"source failed: {exc}")
                self.source.close()
                attempt = 0
                while not self.stopping and not self._open():
                    self._wait(RETRY_BACKOFF_S[min(attempt, len(RETRY_BACKOFF_S) - 1)])
                    attempt += 1
                continue
            if frames is None:
                if self.src_cfg.loop:
                    self.source.close()
                    self._open()
                    continue
                self.set_state(FINALIZED, "source exhausted", normal=True)
                self.beat()
                return 0
            self._send(frames)
            self.beat()
        self.source.close()
        return 0

    def close(self) -> None:
        if self.ring is not None:
            self.ring.close()
        super().close()

    def _fail(self, kind: str, msg: str, *args: object) -> None:
        self.failed[kind] = self.failed.get(kind, 0) + 1
        log.warning(msg, *args)

    def _acquire(self) -> int | None:
        """A free ring slot; a finite source waits for one (back-pressure), a live one never."""
        assert self.ring is not None
        while (slot := self.ring.acquire()) is None:
            choice = when_busy(Busy.RING, finite=self.source.finite, stopping=self.stopping)
            if isinstance(choice, Drop):
                return None
            self._wait(choice.seconds)
        return slot

    def _wait(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while not self.stopping and (left := end - time.monotonic()) > 0:
            time.sleep(min(left, 0.05))
            self.beat()

    def _encode(self, img: np.ndarray) -> np.ndarray:
        try:
            return jpeg.wire_side(img, self.src_cfg.encoding, self.src_cfg.jpeg_quality)
        except ValueError as exc:
            raise SourceError(str(exc)) from None

    def _send(self, f: Frames) -> None:
        h, w = f.left.shape[:2]
        if f.right.shape != f.left.shape:
            self._fail("size", "left %s and right %s differ in shape; pair skipped",
                       f.left.shape, f.right.shape)
            return
        if (w, h) != self.rig.size:  # the workers would fail it: count it here, once
            self.failed["geometry"] = self.failed.get("geometry", 0) + 1
            self.ratelog.warning("geometry", "pair skipped: %s", mismatch(
                (w, h), f"source {self.src_cfg.kind}", self.rig, f"calib {self.rig.id}"))
            return
        left, right = self._encode(f.left), self._encode(f.right)
        slot: int | None = None
        if self.ring is not None:
            slot = self._acquire()
            if slot is None:  # every slot still held by some pool, and no waiting
                self.dropped += 1
                return
            try:
                ref = self.ring.write(slot, left, right)
            except RingError as exc:
                self.ring.release(slot)
                self.failed["too_large"] = self.failed.get("too_large", 0) + 1
                self.ratelog.warning("too_large", "pair does not fit a ring slot; skipped: %s",
                                     exc)
                return
        seq = self.seq
        self.seq += 1
        header = self._header(f, seq)
        payload: list[Any] = [messages.encode(header)]
        payload += [left, right] if slot is None else [messages.encode(ref)]
        while not self._deliver(payload):  # the broker cannot take it now
            choice = when_busy(Busy.BROKER, finite=self.source.finite, stopping=self.stopping)
            if isinstance(choice, Wait):
                self._wait(choice.seconds)
                continue
            if isinstance(choice, Drop):
                self.dropped += 1
                if choice.release and self.ring is not None and slot is not None:
                    self.ring.release(slot)
                return
            unreachable(choice)
        self.produced += 1
        if self.produced == 1:
            self.beat(due=True)  # the supervisor times --duration from the first pair
        if self.image_watch is not None:
            self._watch_image(f, header)
        if f.truth is not None:
            truth = msgspec.structs.replace(f.truth, seq=seq)
            # Truth is for tests and viewers; never worth a wait.
            self._deliver([tap_msgs.TOPIC_TRUTH, messages.encode(truth)])

    def _watch_image(self, f: Frames, header: messages.StereoPair) -> None:
        """A sample for the image-health watch when one is due; its view goes to the broker
        (out of band, never worth a wait: the next sample says it again)."""
        assert self.image_watch is not None
        t_ns = header.t_wall_ns if header.source_time else header.t_mono_ns
        view = self.image_watch.pair(f.left, t_ns / 1e9)
        if view is not None:
            self._deliver([messages.IMAGE_HEALTH, messages.encode(view)])

    def _header(self, f: Frames, seq: int) -> messages.StereoPair:
        """The pair's header, stamped now, with what the motion gate saw in its left image."""
        h, w = f.left.shape[:2]
        seen = self.motion.update(f.left) if self.motion is not None else None
        if seen is not None:
            self._pace(seen.motion or seen.relearnt)
        return messages.StereoPair(
            seq=seq,
            # A recording's own capture time; a camera's is now (a label only).
            t_wall_ns=time.time_ns() if f.t_wall_ns is None else f.t_wall_ns,
            t_mono_ns=time.monotonic_ns(),  # stamped after encoding: transport latency
            source_time=f.t_wall_ns is not None,  # durations on a recording's own stamps
            t_left_ns=f.t_left_ns,
            t_right_ns=f.t_right_ns,
            skew_ns=f.right_minus_left_ns(),
            encoding=self.src_cfg.encoding,
            width=w,
            height=h,
            source=self.src_cfg.kind,
            motion=seen.motion if seen is not None else None,
            motion_score=seen.score if seen is not None else 0.0,
            motion_regions=seen.regions[:MOTION_REGIONS] if seen is not None else (),
        )

    def _pace(self, changed: bool) -> None:
        """Duty cycling: the idle rate, or the full rate from the very next pair."""
        hz = self.duty.pair(changed, time.monotonic())
        if hz is None or self.source.paced:
            return
        self.period_ns = int(1e9 / hz)
        # Back to the full rate: the next pair is due one full period after this one.
        self.next_ns = min(self.next_ns, time.monotonic_ns() + self.period_ns)
        log.debug("capture at %g pairs/s (%s)", hz, "idle" if self.duty.idle else "motion")

    def _deliver(self, frames: list[Any]) -> bool:
        """Hand one message to the broker without waiting; False if it cannot take it now."""
        if self.ring is None:
            try:
                self.push.send_multipart(frames, zmq.NOBLOCK, copy=False)
            except zmq.Again:
                return False
            return True
        link = self.link.get()
        if link is None:
            self.ratelog.warning("link", "broker link: nobody listens at %s", self.link.path)
            return False
        try:
            return link.send(frames)
        except LinkClosed as exc:  # the broker is restarting: drop, reconnect next time
            self.ratelog.warning("link", "broker link: %s", exc)
            self.link.drop()
            return False

