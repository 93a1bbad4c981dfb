"""The broker process: translates sockets to BrokerState events and actions to sends.

Owns: PULL from capture, ROUTER to workers, a local link of results to the
normalizer (in batches), PUB tap (frame metadata, images, stats once a second: its
trapflow.broker.tap.BrokerTap), a PULL of the supervisor's sealed orders (an ipc file in
the run directory), and with network.remote.bind a second ROUTER for workers on other
hosts (CURVE, ZAP: its trapflow.broker.remote.RemoteWorkersSide). Who may send what is
trapflow.broker.trust's to say.
Image frames are forwarded as received (zero-copy); only the small header is
decoded. With the shared-memory ring, capture and local workers talk to it over
local links instead (descriptors only).
"""

from __future__ import annotations

import collections
import logging
import time
from typing import Any

import zmq

from trapflow.broker import trust
from trapflow.broker.links import LinkRegistry
from trapflow.broker.orders import OrdersChannel
from trapflow.broker.preview import PreviewClock, drawn_pools
from trapflow.broker.remote import BrokerHooks, RemoteWorkersSide, frame_bytes
from trapflow.broker.results import ResultsOut, bounded
from trapflow.broker.state import (
    Action,
    BrokerState,
    Dispatch,
    Evicted,
    GateNotice,
    PoolSpec,
    Rejected,
    Release,
)
from trapflow.broker.tap import BrokerTap
from trapflow.broker.trust import LocalMsg
from trapflow.errors import ProtocolError, unreachable
from trapflow.gate.policy import gated_pools
from trapflow.runtime.node import ACTIVE, Node, NodeSpec
from trapflow.runtime.ratelog import RateLimitedLog, wire
from trapflow.wire import control_msgs, frame_msgs, gate_msgs, messages, tap_msgs
from trapflow.wire.frame_ring import FrameRing
from trapflow.wire.links import Link, LinkClosed, Poller
from trapflow.wire.transport import PAIR_MAX_MSG_BYTES, SocketSpec, open_socket, zmq_readable

log = logging.getLogger(__name__)

STATS_INTERVAL_S = 1.0
TICK_INTERVAL_S = 0.1
MAX_GOODBYES = 256  # workers that left on purpose, remembered for the log's level


class BrokerNode(Node):
    """Distributes pairs to worker pools with back-pressure and per-pool policies."""

    def __init__(self, spec: NodeSpec) -> None:
        # Long on purpose: all the broker holds, made in the order each depends on the other.
        super().__init__(spec)
        ep = self.endpoints
        self.poller = Poller()
        self.pull = open_socket(self.ctx, SocketSpec(zmq.PULL, ep.capture, bind=True, rcvhwm=8,
                                                     max_msg_bytes=PAIR_MAX_MSG_BYTES))
        self.router = open_socket(
            self.ctx, SocketSpec(zmq.ROUTER, ep.workers, bind=True, router_mandatory=True)
        )
        self.poller.register(self.pull)
        self.poller.register(self.router)
        self.orders = OrdersChannel(self.ctx, ep.orders, spec.order_key, self.poller)
        self._jobs: dict[tuple[str, int], bytes] = {}
        pools = {  # a remote pool exists with no local worker: remote workers add to count
            name: PoolSpec(p.parsed_policy, p.timeout_s, p.max_pending_age_s, p.max_detections)
            for name, p in self.cfg.pools.items()
            if p.count > 0 or p.remote
        }
        self.state = BrokerState(pools, idle_liveness_s=self.cfg.supervisor.liveness_s,
                                 gates=gated_pools(self.cfg),
                                 paced=self.cfg.source.waits_for_pools)
        self.frames: dict[int, list[Any]] = {}
        # Shared-memory ring: the broker owns slot lifetime (frees a slot on Release).
        ring_name = spec.ring
        self.ring = FrameRing(ring_name) if ring_name else None
        self.refs: dict[int, frame_msgs.FrameRef] = {}
        # Remote pools get JPEG, from their local workers too (the remote side encodes it).
        self.remote_pools = {n for n, p in self.cfg.pools.items() if p.remote}
        if self.ring is not None and spec.restarted and (n := self.ring.free_held()):
            log.warning("freed %d ring slots held by a previous broker", n)
        # Local links: the normalizer's always; capture's and local workers' with the ring.
        self.links = LinkRegistry(self.poller)
        self.links.listen(ep.results_link, "results")
        if self.ring is not None:
            self.links.listen(ep.capture_link, "capture")
            self.links.listen(ep.workers_link, "worker")
        self.ratelog = RateLimitedLog(log)
        self.remote = RemoteWorkersSide(
            self.cfg, spec.the_rig, self.ctx, self.poller, self.state, self.ratelog,
            BrokerHooks(apply=self._apply, refuse=self._refuse, goodbye=self._goodbye,
                        on_worker_msg=self._on_worker_msg, payload=self._payload))
        self.tap = BrokerTap(self.ctx, ep.tap, self.poller, self.state, self.remote.roster,
                             started=time.monotonic(), preview=PreviewClock(
                                 1.0 / self.cfg.viewer.frame_hz, drawn_pools(self.cfg.pools)))
        self.results = ResultsOut(self.ratelog)  # to the normalizer, until acknowledged
        # Refused from the wire, by reason (forged answers are counted in self.state.rejected).
        self.refused: dict[str, int] = {}
        self.malformed = 0
        self.unroutable = 0
        # A planned stop began (the supervisor said so): workers leave, none of it is news.
        self.winding_down = False
        # Workers that said a planned goodbye (stop, recycle), newest last (bounded).
        self._goodbyes: collections.OrderedDict[bytes, str] = collections.OrderedDict()
        # The ladder's level, as the supervisor last said (for Stats): the first level at
        # the run's start; unknown after a restart until the supervisor tells it again.
        ladder = self.cfg.ladder
        self.level = ladder.levels[0].name if ladder.enabled and not spec.restarted else ""
        self.image: messages.ImageHealth | None = None  # capture's latest image-health view
        self.level_reason = ""

    def counters(self) -> dict[str, int]:
        active, idle = self.state.gate_time()
        return {"pairs_in": self.state.pairs_in, "malformed": self._malformed(),
                "gate_active_s": int(active), "gate_idle_s": int(idle),
                "held": self.state.held(), "results_waiting": self.results.waiting(),
                "results_dropped": self.results.dropped, "late_answers": self.state.late,
                "refused_subscriptions": self.tap.gate.refused, **self.remote.counters(),
                "previews": self.tap.preview.published, "previews_failed": self.tap.preview_failed,
                **{f"rejected_{k}": n for k, n in self.state.rejected.items()},
                **{f"refused_{k}": n for k, n in self.refused.items()}}

    def run(self) -> int:
        self.set_state(ACTIVE)
        poller = self.poller
        next_tick = time.monotonic()
        while not self.stopping:
            socks, fds = poller.poll(int(TICK_INTERVAL_S * 1000))
            if self.orders.sock in socks:
                for order in self.orders.drain(self._forged_order):
                    self._on_order(order, time.monotonic())
            if self.router in socks:
                self._drain_workers()
            self.remote.serve(socks)
            for ready in self.links.ready(fds):
                if isinstance(ready, Link):
                    self._drain_link(ready)
                else:
                    self._accept(ready)
            if self.pull in socks:
                self._drain_capture()
            if self.state.paced:
                self._pace_capture()
            if self.tap.sock in socks:
                self.tap.on_subscriptions()
            self._flush_results()
            now = time.monotonic()
            if now >= next_tick:
                next_tick = now + TICK_INTERVAL_S
                self._apply(self.state.tick(now))
                self.remote.evict_silent_hosts(now)
                if self.tap.stats_due(now, STATS_INTERVAL_S):
                    self._publish_stats(now)
                self.beat()
        self.state.finish()  # what is still pending or in flight will never be processed
        self._flush_results()
        self._publish_stats(time.monotonic())  # the run's totals, for the supervisor
        self.links.close()
        return 0

    # --- capture side ---------------------------------------------------------------

    def _pace_capture(self) -> None:
        """Capture's links are not polled while a pool is full, and read again once all have
        room (nor is a zmq capture socket read: it fills to its high-water mark)."""
        full = self.state.holds_source()
        for link in self.links.links("capture"):
            if full:
                self.links.hold(link)
            elif self.links.release(link):
                self._drain_link(link)  # what waited while it was not polled
        if not full:
            self._drain_capture()

    def _drain_capture(self) -> None:
        # Take what is queued now, then go back to the workers: results never starve.
        # EVENTS before each recv: an empty socket costs no exception (this is the hot path).
        for _ in range(64):
            if self.state.holds_source():
                return  # held back, and not touched: it costs no pass until there is room
            self.poller.touch(self.pull)  # read its events again next pass: more may wait
            if not zmq_readable(self.pull):
                return
            self._on_capture(self.pull.recv_multipart(copy=False))

    def _on_capture(self, frames: list[Any]) -> None:
        if len(frames) == 2 and frame_bytes(frames[0]) == tap_msgs.TOPIC_TRUTH:
            self.tap.publish(tap_msgs.TOPIC_TRUTH, frames[1])  # out of band, for the tap only
            return
        if len(frames) == 2 and frame_bytes(frames[0]) == messages.IMAGE_HEALTH:
            try:  # out of band: capture's image-health view, in the next Stats
                self.image = messages.decode_image_health(frame_bytes(frames[1]))
            except ProtocolError as exc:
                self.malformed += 1
                self.ratelog.warning("capture", "dropped malformed image health: %s", exc)
            return
        ref: frame_msgs.FrameRef | None = None
        try:
            if len(frames) == 2:
                pair, ref = frame_msgs.check_pair_ref(frames)
                if self.ring is None:
                    raise ProtocolError("pair: got a frame ref, but no shared-memory ring")
                self.ring.validate(ref)
            else:
                pair = messages.check_pair_frames(frames)
        except ProtocolError as exc:
            self.malformed += 1
            self.ratelog.warning("capture", "dropped malformed pair message: %s", exc)
            return
        if pair.seq in self.frames:
            self.malformed += 1
            self.ratelog.warning("dup", "dropped pair with duplicate seq %d", pair.seq)
            if ref is not None and self.ring is not None and ref != self.refs.get(pair.seq):
                self.ring.free_ref(ref)
            return
        self.frames[pair.seq] = frames
        if ref is not None:
            self.refs[pair.seq] = ref
        if self.tap.wanted.get(tap_msgs.TOPIC_META):
            self.tap.publish(tap_msgs.TOPIC_META, frames[0])
        if self.tap.wanted.get(tap_msgs.TOPIC_IMAGE):
            self.tap.publish(tap_msgs.TOPIC_IMAGE, *self._payload(pair.seq, copy=True))
        self._preview(pair.seq, None)
        self._apply(self.state.pair_arrived(pair.seq, time.monotonic(), pair.motion,
                                            pair.motion_score, pair.t_left_ns / 1e9))

    # --- local links ----------------------------------------------------------------

    def accept(self, role: str) -> list[Link]:
        """Accept every peer waiting on a role's listener (the step the loop takes when the
        listener is readable, public for in-process tests): the links now registered."""
        return self._accept(self.links.listener_of(role))

    def _accept(self, listener: Any) -> list[Link]:
        role = self.links.listeners[listener]
        accepted = []
        for link in self.links.pending(listener):
            if role == "results":  # a (restarted) normalizer: it gets what waited for it
                if self.links.results_link is not None:
                    self._drain_link(self.links.results_link)  # a dead predecessor's EOF
                if self.links.results_link is not None:  # one normalizer at a time
                    self._refuse("second_normalizer",
                                 "refused a second connection to the results link while the "
                                 "normalizer's is live; only one normalizer may run")
                    link.close()
                    continue
            self.links.add(link, role)
            accepted.append(link)
        return accepted

    def _drain_link(self, link: Link) -> None:
        role = self.links.role(link)
        if role is None:  # dropped earlier in this pass (a failed send to it)
            return
        for _ in range(256):
            if role == "capture" and self.state.holds_source():
                return  # the rest waits in the link; _pace_capture reads it later
            try:
                frames = link.recv()
                if frames is None:
                    return
                if role == "capture":
                    self._on_capture(frames)
                    continue
                if role == "results":
                    self._on_ack(gate_msgs.decode_normalizer_msg(frames[0]))
                    continue
                msg = trust.local_msg(messages.decode_worker_msg(frames[0]))
                ident = self.links.ident(link)
                if ident is None:  # a worker names itself in its first message
                    name = trust.names_link(msg)
                    if isinstance(name, trust.Refuse):
                        raise ProtocolError(name.text())
                    ident = name.encode()
                    if not self.links.name(link, ident):  # that name is another live link's
                        self._refuse("duplicate_worker",
                                     "refused a worker link naming itself '%s': a live link "
                                     "has that name; every worker process has its own",
                                     wire(name))
                        self._drop_link(link, "duplicate name")
                        return
                self._on_worker_msg(ident, msg, [ident, *frames])  # as a ROUTER gives them
            except LinkClosed:
                self._drop_link(link, "disconnected")
                return
            except ProtocolError as exc:
                self.malformed += 1
                self.ratelog.warning("link", "dropped malformed %s message: %s", role, exc)

    def _drop_link(self, link: Link, reason: str) -> None:
        """A local peer went away: a worker's jobs are settled now, not at a timeout."""
        removed = self.links.remove(link)
        if removed is None:  # removed earlier in this pass
            return
        if removed.was_results:
            self.results.link_lost()
        if removed.ident is not None:
            self._apply(self.state.worker_gone(removed.ident, reason, time.monotonic()))

    # --- worker side ----------------------------------------------------------------

    def _drain_workers(self) -> None:
        self.poller.touch(self.router)
        for _ in range(256):
            if not zmq_readable(self.router):
                return
            frames = self.router.recv_multipart(copy=False)
            ident = frames[0].bytes
            try:
                if len(frames) < 2:
                    raise ProtocolError(
                        f"worker message: expected 2 or 3 frames, got {len(frames)}")
                msg = trust.local_msg(messages.decode_worker_msg(frames[1]))
                self._on_worker_msg(ident, msg, frames)
            except ProtocolError as exc:
                self.malformed += 1
                self.ratelog.warning("worker", "dropped malformed worker message: %s", exc)

    def _on_worker_msg(self, ident: bytes, msg: LocalMsg, frames: list[Any]) -> None:
        verdict = trust.on_workers_socket(ident, msg)
        if isinstance(verdict, trust.Refuse):
            self._refuse(verdict.reason, verdict.message, *verdict.args)
            return
        now = time.monotonic()
        if isinstance(msg, messages.Ready):
            self._apply(self.state.worker_ready(ident, msg.pool, msg.credit, now))
        elif isinstance(msg, messages.Alive):
            self._apply(self.state.worker_seen(ident, msg.pool, msg.free, now))
        elif isinstance(msg, messages.Done):
            if len(frames) != 3:
                raise ProtocolError(
                    f"done: expected 3 frames [id, done, result], got {len(frames)}")
            # Read, not forwarded unread: its seq and pool must be the Done's (issue 26).
            result = messages.decode_result(frames[2])
            actions = self.state.job_done(ident, msg.pool, msg.seq, True, now,
                                          named=(result.seq, result.pool))
            if not any(isinstance(a, Rejected) for a in actions):
                # only an answer to a job this worker was given, bounded before it goes on
                limit = self.cfg.pools[msg.pool].max_detections
                kept, cut = bounded(result, limit)
                if cut:
                    self.state.detections_cut(msg.pool, cut)
                    self.ratelog.warning("cut:" + msg.pool, "pool %s: a result brought %d "
                                         "detections, over its max_detections: the %d least "
                                         "confident were cut (counted as boxes_cut)", msg.pool,
                                         limit + cut, cut)
                self.results.add(messages.encode(kept) if cut else frames[2])
                self.remote.roster.processed(ident)
            self._apply(actions)
        elif isinstance(msg, messages.Gone):
            self._on_gone(msg, now, notice=False)  # a worker's own goodbye (trust checked)
        elif isinstance(msg, (messages.Stopping, messages.PoolSwitch, messages.LadderLevel)):
            raise AssertionError("trust refuses the supervisor's orders on the workers socket")
        elif isinstance(msg, messages.Failed):
            actions = self.state.job_done(ident, msg.pool, msg.seq, False, now, msg.kind)
            if not any(isinstance(a, Rejected) for a in actions):
                self.ratelog.warning("failed:" + msg.pool, "%s failed pair %d: %s",
                                     wire(msg.worker), msg.seq, wire(msg.reason))
            self._apply(actions)
        else:
            unreachable(msg)

    # --- the supervisor's orders -------------------------------------------------------

    def _forged_order(self, why: str) -> None:
        self._refuse("forged_order", "refused a message on the supervisor's channel: %s",
                     wire(why))

    def _on_order(self, order: control_msgs.SupervisorOrder, now: float) -> None:
        """An order the supervisor sealed (open_order checked the seal)."""
        if isinstance(order, messages.Gone):
            self._on_gone(order, now, notice=True)
        elif isinstance(order, messages.Stopping):
            self.winding_down = True
            log.debug("planned stop: workers leave from now on")
        elif isinstance(order, messages.PoolSwitch):
            self._on_pool_switch(order, now)
        elif isinstance(order, messages.LadderLevel):
            self.level, self.level_reason = order.level, order.reason  # in the next Stats
        else:
            unreachable(order)

    def _on_gone(self, msg: messages.Gone, now: float, notice: bool) -> None:
        """A worker left: its own goodbye, or the supervisor's notice of its exit."""
        gone = msg.worker.encode()
        link = self.links.worker(gone)
        if notice and link is not None:
            # Read what the worker sent before it exited first (its last answer and
            # goodbye): the supervisor's notice must not overtake them.
            self._drain_link(link)
        self._goodbye(gone, msg.reason)
        self._apply(self.state.worker_gone(gone, msg.reason, now, requeue=msg.reason.startswith(
            messages.GONE_RECYCLED)))

    def close(self) -> None:
        self.links.close()
        self.remote.close()
        super().close()

    def _on_pool_switch(self, msg: messages.PoolSwitch, now: float) -> None:
        """Runtime control of a pool, from the supervisor (trust checked who sent it)."""
        try:
            actions, done = self.state.pool_switch(msg.pool, msg.active, msg.policy,
                                                   msg.min_interval_s, now)
        except ValueError as exc:
            self.ratelog.warning("switch", "refused a pool switch: %s", wire(str(exc)))
            return
        self._apply(actions)
        for what in done:
            log.info("pool %s %s", msg.pool, what)
        if msg.params is not None:
            self._configure_workers(msg.pool, msg.params)

    def _configure_workers(self, pool: str, params: dict[str, Any]) -> None:
        """New parameters, applied in place by every worker of the pool between pairs."""
        frame = messages.encode(messages.Configure(pool=pool, params=params))
        for ident in self.state.pool_workers(pool):
            link = self.links.worker(ident)
            try:
                if link is not None:
                    link.send([frame])
                else:
                    self.router.send_multipart([ident, frame])
            except (zmq.ZMQError, LinkClosed) as exc:  # it is gone: its successor starts
                self._unreachable("configure", ident, link, exc,
                                  remote=self.remote.is_remote(ident))
        log.info("pool %s: new parameters sent to its workers", pool)

    # --- actions --------------------------------------------------------------------

    def _apply(self, actions: list[Action]) -> None:
        # Long on purpose: one branch per action kind, each the socket work of that kind;
        # the exhaustive chain (ending in unreachable) reads best in one place.
        for action in actions:
            if isinstance(action, Dispatch):
                key = (action.pool, action.gap)
                job = self._jobs.get(key)
                if job is None:  # almost always gap 0: encode each pool's job frame once
                    job = messages.encode(messages.Job(pool=action.pool, gap=action.gap))
                    if action.gap == 0:
                        self._jobs[key] = job
                link = self.links.worker(action.worker)
                try:
                    if self.remote.is_remote(action.worker):
                        self.remote.send_job(action.worker, job, action.seq)
                    elif link is not None:
                        if not link.send([job, *self.frames[action.seq]]):
                            raise LinkClosed("its queue is full")
                    else:
                        remote = action.pool in self.remote_pools
                        self.poller.touch(self.router)
                        payload = (self.remote.jpeg_payload(action.seq) if remote
                                   else self._payload(action.seq, copy=False))
                        self.router.send_multipart([action.worker, job, *payload], copy=False)
                    self._preview(action.seq, action.pool)
                except (zmq.ZMQError, LinkClosed) as exc:  # EHOSTUNREACH: the worker vanished
                    self.unroutable += 1
                    self._unreachable("route", action.worker, link, exc,
                                      remote=self.remote.is_remote(action.worker))
                    if link is not None:
                        self._drop_link(link, "unreachable")
                    else:
                        self._apply(self.state.worker_gone(action.worker, "unreachable",
                                                           time.monotonic()))
            elif isinstance(action, Release):
                self.frames.pop(action.seq, None)
                self.remote.release(action.seq)
                ref = self.refs.pop(action.seq, None)
                if ref is not None and self.ring is not None:
                    self.ring.free_ref(ref)
            elif isinstance(action, Rejected):
                if action.named is None:
                    why = "it was not dispatched to that worker or was answered already"
                else:
                    why = (f"its result names pair {action.named[0]} of pool "
                           f"'{wire(action.named[1])}': expected that pair of that pool")
                self.ratelog.warning(
                    "rejected:" + action.reason,
                    "dropped an answer from worker '%s' for pool '%s' pair %d (%s): %s",
                    wire(action.worker), wire(action.pool), action.seq, action.reason, why)
            elif isinstance(action, GateNotice):
                log.info("%s", action.text)
            elif isinstance(action, Evicted):
                self.remote.roster.evicted(action.worker, action.reason)
                # A worker told to stop, or recycled, leaves on purpose (news for the debug
                # log only); anything else is news.
                level = (logging.DEBUG if messages.is_planned_goodbye(action.reason)
                         else logging.WARNING)
                self.ratelog.log(
                    level, f"evicted:{level}", "evicted worker %s of pool %s (%s); pairs lost: %s",
                    wire(action.worker), action.pool, wire(action.reason),
                    list(action.lost) or "none",
                )
            else:
                unreachable(action)

    def _malformed(self) -> int:
        """Malformed messages dropped, from every socket and link (the remote side counts
        its own)."""
        return self.malformed + self.remote.malformed

    def _publish_stats(self, now: float) -> None:
        self.tap.publish_stats(now, self._malformed(), self.level, self.level_reason,
                               self.image)

    def _goodbye(self, ident: bytes, reason: str) -> None:
        """Remember a worker that left on purpose: a send to it afterwards is no news."""
        if messages.is_planned_goodbye(reason):
            self._goodbyes[ident] = reason
            while len(self._goodbyes) > MAX_GOODBYES:
                self._goodbyes.popitem(last=False)

    def _unreachable(self, what: str, ident: bytes, link: Link | None, exc: Exception,
                     remote: bool = False) -> None:
        """A send to a worker failed. What the worker sent last is read first (its local
        link, or the socket it used): its goodbye may wait there, unread, behind the answer
        that gave it the credit (it answered, said goodbye and left before the broker read
        the answer). A worker that left on purpose, or any during a planned stop, is debug;
        anything else is a real failure mid-run (a warning)."""
        if link is not None:
            self._drain_link(link)  # its Gone (and EOF) settle it as it meant to leave
        elif remote:
            self.remote.drain()
        else:
            self._drain_workers()
        if self.winding_down or ident in self._goodbyes:
            log.debug("cannot reach worker %r, which is leaving: %s", ident, exc)
        else:
            self.ratelog.warning(what, "cannot reach worker %r: %s", ident, exc)

    def _flush_results(self) -> None:
        try:
            self.results.flush(self.links.results_link)
        except LinkClosed:
            assert self.links.results_link is not None
            self._drop_link(self.links.results_link, "disconnected")

    def _on_ack(self, ack: gate_msgs.NormalizerMsg) -> None:
        """Only the live normalizer's link is read for acks; never more than it was sent. Its
        gate hints (live tracks, a moving rig) go to the gate."""
        if isinstance(ack, gate_msgs.GateHint):
            self._apply(self.state.gate_hint(ack.tracks, ack.rig_moving, time.monotonic()))
            return
        sent = len(self.results.unacked)
        if not self.results.acked(ack.count):
            self._refuse("bad_ack", "an acknowledgement of %d results exceeds the %d sent and "
                         "not yet acknowledged; taking only those", ack.count, sent)

    def _refuse(self, reason: str, msg: str, *args: object) -> None:
        self.refused[reason] = self.refused.get(reason, 0) + 1
        self.ratelog.warning("refused:" + reason, msg, *args)

    def _payload(self, seq: int, copy: bool) -> list[Any]:
        """[header, left, right] bytes, or [header, ref] for local readers of the ring.

        copy=True reads the bytes out of the ring (remote pools, the tap): zmq sends them
        later from its own thread, after the slot may have been freed and reused.
        """
        frames = self.frames[seq]
        ref = self.refs.get(seq)
        if ref is None or not copy:
            return frames
        assert self.ring is not None
        row = self.ring.payload(ref)
        return [frames[0], bytes(row[0]), bytes(row[1])]

    def _preview(self, seq: int, pool: str | None) -> None:
        """The viewer's preview of a pair that arrived (pool None) or was given to pool,
        if it is the one due (trapflow.broker.preview): from views of the ring (encoded
        before this returns, while the broker still holds the slot) or the frames."""
        if not self.tap.preview_due(pool, time.monotonic()):
            return  # no page open (the usual case: one attribute read per pair)
        frames, ref = self.frames[seq], self.refs.get(seq)
        sides = self.ring.payload(ref) if ref is not None and self.ring is not None else frames[1:]
        self.tap.publish_preview(frames[0], *sides)
