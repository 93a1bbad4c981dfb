"""The normalizer process: every result becomes JSON lines in results.jsonl and on its tap;
detections are tracked on the way (track ids on their lines, tracks.jsonl, counts.jsonl),
with the rig's motion from VO's poses taken out of their speeds.

Owns a local link that brings batches of results from the broker and a PUB of JSON
lines (`result` topic).
Each batch is written unbuffered as it arrives; the batches of one pass are then
acknowledged together (one wake-up of the broker). The file is fsynced every
fsync_interval_s.
"""

from __future__ import annotations

import logging
import os
import time
from typing import IO, Any

import zmq

from trapflow.errors import ProtocolError
from trapflow.gate.hint import HintPacer, RigMotion
from trapflow.gate.policy import gated_pools, rig_config
from trapflow.modem import thumb
from trapflow.modem.frame import max_body
from trapflow.modem.outbox import Outbox, OutboxFull
from trapflow.normalizer import checkpoint
from trapflow.normalizer.result_json import dumps, link_record, normalize
from trapflow.runtime.files import append_whole, is_disk_full, write_atomically
from trapflow.runtime.node import ACTIVE, FINALIZED, Node, NodeSpec, release_memory
from trapflow.runtime.ratelog import RateLimitedLog
from trapflow.tracking.rigpose import RigPoses
from trapflow.tracking.stage import Observations, Observer
from trapflow.wire import gate_msgs, messages, tap_msgs
from trapflow.wire.endpoints import set_file_mode
from trapflow.wire.links import LINK_RETRY_S, LinkClient, LinkClosed
from trapflow.wire.tap_gate import TAP_RCVHWM, TapGate
from trapflow.wire.transport import SocketSpec, open_socket

log = logging.getLogger(__name__)

# Distinct (pool, kind) routes reported to the supervisor (the run ledger counts results.jsonl
# by kind); a plugin inventing result names cannot grow the heartbeat without limit.
MAX_ROUTES = 64


class NormalizerNode(Node):
    """Turns Result messages into compact JSON lines."""

    def __init__(self, spec: NodeSpec) -> None:
        super().__init__(spec)
        ep = self.endpoints
        self.link = LinkClient(ep.results_link)  # results from the broker
        self.link_lost = False  # the link closed; said when it comes back
        # A tap that remembers only prefixes of its one topic (TapGate), whoever subscribes.
        self.pub = open_socket(self.ctx, SocketSpec(zmq.XPUB, ep.results_tap, bind=True,
                                                    sndhwm=256, rcvhwm=TAP_RCVHWM,
                                                    xpub_manual=True))
        self.gate = TapGate(self.pub, (tap_msgs.TOPIC_RESULT,))
        ncfg = self.cfg.normalizer
        self.path = spec.run_dir / ncfg.results_file
        # Unbuffered: a batch is in the kernel (safe from a crash of this process) before it is
        # acknowledged; fsync (power cuts) follows on its interval.
        self.file: IO[bytes] = open(self.path, "ab", buffering=0)  # noqa: SIM115
        set_file_mode(self.path)  # 0640 whatever the umask
        # With a modem, every result is stored durably before anything tries to send it.
        self.outbox: Outbox | None = None
        if self.cfg.modem.enabled:
            self.outbox = Outbox(spec.run_dir / self.cfg.outbox.path, self.cfg.outbox)
        # One tracker per detector pool; finished tracks and counts go to their own files.
        self.observers: dict[str, Observer] = {}
        # A run started again in its run directory (after a power cut) goes on with the
        # tracks, open interval and news memory it had (normalizer/checkpoint.py).
        self.saved_at = time.monotonic()  # when the observation state was last saved
        self.fed = False  # pairs tracked since
        # VO's poses, which every tracker uses for its tracks' speed over the ground; one
        # VO pool's chain only (two pools' worlds are not the same frame).
        self.rig_poses = RigPoses()
        self.vo_pool: str | None = None
        self.obs_files: dict[str, IO[bytes]] = {}
        if self.cfg.observe.enabled:
            names = [self.cfg.observe.tracks_file, self.cfg.observe.counts_file]
            if self.cfg.review.enabled:
                names.append(self.cfg.review.file)
            for name in names:
                path = spec.run_dir / name
                self.obs_files[name] = open(path, "ab", buffering=0)  # noqa: SIM115
                set_file_mode(path)
        self.tracks = 0
        self.reviews = self.thumbnails = 0  # tracks queued for review; thumbnails queued
        if self.obs_files:
            self.observers = checkpoint.load(spec.run_dir)
            for obs in self.observers.values():
                obs.poses = self.rig_poses
        # With a gated pool, the broker's gate hears of live tracks and of a moving rig.
        self.rig: RigMotion | None = None
        if gated_pools(self.cfg):
            self.rig = RigMotion(rig_config(self.cfg))
        self.hints = HintPacer()
        self.tracked_at = 0.0  # monotonic time detections were last tracked
        self.refused = 0
        self.lines = 0
        self.malformed = 0
        self.routes: set[str] = set()  # route:<pool>:<kind>: a pool's results become these lines
        # Lines a full disk kept out of each file (ledger.json's not_written_disk_full): the
        # run goes on (the taps, VO, the modem) and what could not be written is counted.
        self.disk_full: dict[str, int] = {}
        self.full_now = False  # the last write found the disk full
        self.ratelog = RateLimitedLog(log)

    def counters(self) -> dict[str, int]:
        out = {"lines": self.lines, "malformed": self.malformed, "outbox_refused": self.refused,
               "tracks": self.tracks, "reviews": self.reviews,
               "thumbnails": self.thumbnails,
               "late_for_tracking": sum(o.late for o in self.observers.values()),
               "capped_for_tracking": sum(o.capped for o in self.observers.values()),
               "refused_subscriptions": self.gate.refused}
        out.update(dict.fromkeys(self.routes, 1))
        out.update({f"disk_full:{name}": n for name, n in self.disk_full.items()})
        return out

    def _append(self, name: str, fh: IO[bytes], data: bytes, lines: int) -> None:
        """Append whole lines to one of the run's files; on a full disk count them as not
        written (said once, and once more when the disk has room again)."""
        if append_whole(fh, data):
            if self.full_now:
                self.full_now = False
                log.warning("the disk has room again: %s written again", name)
            return
        if not self.full_now:
            log.error("the disk of the run directory is full: lines of %s are not written, "
                      "only counted (ledger.json's not_written_disk_full); the run goes on",
                      name)
        self.full_now = True
        self.disk_full[name] = self.disk_full.get(name, 0) + lines

    def run(self) -> int:
        ncfg = self.cfg.normalizer
        self.set_state(ACTIVE)
        next_flush = next_sync = time.monotonic()
        dirty = False
        while not self.stopping:
            dirty |= self._receive(100)
            self._hint(time.monotonic())
            self.gate.drain()  # subscriptions to the results tap
            now = time.monotonic()
            if self.gate.trim_due(now):
                release_memory()  # what refused subscribers made libzmq hold, once they leave
            if dirty and now >= next_flush:
                self.file.flush()
                next_flush = now + ncfg.flush_interval_s
                if now >= next_sync:
                    self._fsync(self.file)
                    next_sync = now + ncfg.fsync_interval_s
                dirty = False
            if self.fed and now - self.saved_at >= checkpoint.CHECKPOINT_S:
                self._save()
            self.beat()
        # Take what the broker already sent before closing the file.
        while self.link.link is not None and self._receive(0):
            pass
        ended = [obs.finish() for obs in self.observers.values()]  # live tracks end now
        if self.observers:
            self._save()  # the news memory stays for a run started again here
        for got in ended:
            self._write_observations(got)
        for fh in (self.file, *self.obs_files.values()):
            fh.flush()
            self._fsync(fh)
            fh.close()
        if self.outbox is not None:
            self.outbox.close()
        self.set_state(FINALIZED)
        return 0

    def _save(self) -> None:
        """Save the observation state (live tracks, open interval, news memory)."""
        if not checkpoint.save(self.spec.run_dir, self.observers):
            self.ratelog.warning("checkpoint", "observation state not saved: the disk is full")
        self.saved_at, self.fed = time.monotonic(), False

    def _fsync(self, fh: IO[bytes]) -> None:
        """fsync one file; a full disk (some filesystems say so only here) is logged."""
        try:
            os.fsync(fh.fileno())
        except OSError as exc:
            if not is_disk_full(exc):
                raise
            self.ratelog.warning("fsync", "fsync of %s: the disk is full", fh.name)

    def _receive(self, timeout_ms: int) -> bool:
        """Handle the batches of results waiting (up to timeout_ms for the first)."""
        link = self.link.get()
        if link is None:  # the broker is not listening yet (or restarting)
            time.sleep(LINK_RETRY_S)
            return False
        if self.link_lost:  # only a link that comes back says the broker restarted
            self.link_lost = False
            log.info("results link: reconnected to the broker")
        dirty = False
        written = 0
        try:
            if not link.wait(timeout_ms):
                return False
            for _ in range(256):
                try:
                    batch = link.recv()
                except ProtocolError as exc:
                    self.malformed += 1
                    self.ratelog.warning("link", "dropped malformed results batch: %s", exc)
                    continue
                if batch is None:
                    break
                lines: list[bytes] = []
                for data in batch:  # the broker sends a pass's results together
                    dirty |= self._handle(data, lines)
                if lines:
                    self._append(self.path.name, self.file, b"".join(lines), len(lines))
                written += len(batch)
            if written:  # one acknowledgement for all the batches written in this pass
                link.send([messages.encode(messages.ResultsAck(count=written))])
        except LinkClosed as exc:  # a new broker will listen at the same path
            # At a normal stop the broker goes first: a closed link is news only once a
            # new broker answers (above).
            log.debug("results link: %s; reconnecting", exc)
            self.link_lost = True
            self.link.drop()
            self.hints.forget()
        return dirty

    def _hint(self, now: float) -> None:
        """Tell the broker's gate how many tracks are alive and whether the rig moves, when
        that changes and again every second while either holds it open."""
        link = self.link.link
        if self.rig is None or link is None:
            return
        # Tracks end only when a detection comes; with none for max_gap_s none is alive.
        fresh = now - self.tracked_at <= self.cfg.observe.max_gap_s
        tracks = sum(o.tracker.alive for o in self.observers.values()) if fresh else 0
        if self.hints.due(tracks, self.rig.moving, now):
            try:
                link.send([messages.encode(gate_msgs.GateHint(tracks=tracks,
                                                              rig_moving=self.rig.moving))])
            except LinkClosed as exc:  # _receive reconnects
                log.debug("results link: %s", exc)
                self.hints.forget()

    def _handle(self, data: messages.Buffer, lines: list[bytes]) -> bool:
        """Decode, normalize and store one result; its JSON lines join `lines`."""
        try:
            res = messages.decode_result(data)
            objs = normalize(res, self.cfg.normalizer.decimals)
        except (ProtocolError, TypeError) as exc:
            self.malformed += 1
            self.ratelog.warning("result", "dropped malformed result: %s", exc)
            return False
        if (self.obs_files and isinstance(res.body, messages.StereoVO)
                and self.vo_pool in (None, res.pool)):
            self.vo_pool = res.pool
            b = res.body
            self.rig_poses.add(res.capture_ns() / 1e9, b.pose, b.ok, b.reinit)
        if self.obs_files and isinstance(res.body, messages.MonoIR):
            observer = self.observers.get(res.pool)
            if observer is None:
                observer = self.observers[res.pool] = Observer(
                    self.cfg.observe, self.rig_poses, self.cfg.review, res.pool)
            items = [obj["mono_ir"] for obj in objs]
            capped = observer.capped
            got = observer.feed(res.capture_ns(), items, res.t_wall_ns)
            self._offer_views(observer, res, items)
            self.fed = True
            if got.tracks or got.counts or got.news:
                self._save()  # before they are written or sent: never twice after a cut
            self._write_observations(got)
            if observer.capped and not capped:  # said once per pool, then only counted
                log.warning("pool %s: a pair brought %d boxes, more than observe.max_boxes "
                            "(%d): tracking takes the most confident, the rest get track "
                            "null (counted as capped_for_tracking; said once)", res.pool,
                            len(items), self.cfg.observe.max_boxes)
            self.tracked_at = time.monotonic()
        elif self.rig is not None and isinstance(res.body, messages.StereoVO):
            vo = res.body
            if self.rig.vo(res.capture_ns() / 1e9, vo.ok and not vo.reinit, vo.rotation,
                           vo.translation) is not None:
                log.debug("visual odometry: the rig %s", "moves" if self.rig.moving
                          else "is still")
        if self.outbox is not None:
            sent = [link_record(o) for o in objs] if (self.cfg.modem.detections or not objs
                                                      or "mono_ir" not in objs[0]) else []
            try:
                self.outbox.append_many(sent)
            except OutboxFull as exc:
                self.refused += len(sent)
                self.ratelog.warning("outbox", "outbox refused %d records: %s", len(sent), exc)
        if objs and len(self.routes) < MAX_ROUTES:
            self.routes.add(f"route:{res.pool}:{next(iter(objs[0]))}")
        for obj in objs:
            line = dumps(obj)
            lines.append(line + b"\n")
            self.lines += 1
            try:
                self.pub.send_multipart([tap_msgs.TOPIC_RESULT, line], zmq.NOBLOCK)
            except zmq.Again:
                pass
        return True

    @staticmethod
    def _offer_views(observer: Observer, res: messages.Result,
                     items: list[dict[str, Any]]) -> None:
        """The worker's crops of a result's boxes (matched to them by box) offered as their
        tracks' best views; a box of no confirmed track offers nothing."""
        body = res.body
        reviewer = getattr(observer, "reviewer", None)
        if reviewer is None or not isinstance(body, messages.MonoIR) or not body.views:
            return
        crops = {v.box: v for v in body.views}
        for det, item in zip(body.detections, items, strict=False):
            view = crops.get(det.box)
            if view is not None and item.get("track") is not None:
                reviewer.offer_crop(item["track"], det.confidence, det.box, view.sharpness,
                                    view.jpeg, res.t_wall_ns / 1e9)

    def _write_reviews(self, reviews: list[dict[str, Any]]) -> None:
        """Tracks queued for review: each best view's crop as review/POOL-TRACK.jpg, and a
        line in review.jsonl naming it (written whatever the modem does)."""
        rcfg = self.cfg.review
        lines = []
        for rec in reviews:
            line = dict(rec["review"])
            jpeg = line.pop("jpeg", None)
            if jpeg:
                name = f"{line['pool']}-{line['track']}.jpg"
                folder = self.spec.run_dir / rcfg.folder
                try:
                    folder.mkdir(exist_ok=True)
                    write_atomically(folder / name, jpeg)
                    line["crop"] = f"{rcfg.folder}/{name}"
                except OSError as exc:
                    self.ratelog.warning("review", "review crop %s not written: %s", name, exc)
            if jpeg and (sent := self._send_thumbnail(line["track"], jpeg)):
                line["thumbnail"] = sent
            lines.append(dumps({"review": line}) + b"\n")
        self._append(rcfg.file, self.obs_files[rcfg.file], b"".join(lines), len(lines))
        self.reviews += len(lines)

    def _send_thumbnail(self, track: int, jpeg: bytes) -> dict[str, int] | None:
        """A queued track's crop fitted to `review.thumbnail_bytes`, its packets (each
        decodes on its own) into the outbox as `thumb` records (docs/review.md); what was
        queued (its review line's `thumbnail`), or None."""
        budget = self.cfg.review.thumbnail_bytes
        if self.outbox is None or budget <= 0:
            return None
        most = thumb.max_packet(max_body(self.cfg.modem.max_frame_payload))
        records = thumb.records(track, jpeg, budget, most)
        if not records:
            self.ratelog.warning("thumb", "track %d: no thumbnail fits %d bytes", track, budget)
            return None
        try:
            self.outbox.append_many(records)
        except OutboxFull as exc:
            self.refused += len(records)
            self.ratelog.warning("outbox", "outbox refused %d records: %s", len(records), exc)
            return None
        self.thumbnails += 1
        first = records[0][thumb.RECORD]
        return {"bytes": thumb.cost(records),
                "packets": len(records), "width": first["width"], "height": first["height"],
                "quality": first["quality"]}

    def _write_observations(self, obs: Observations) -> None:
        """Finished tracks and closed intervals to their files (unbuffered, as results)."""
        ocfg = self.cfg.observe
        for name, objs in ((ocfg.tracks_file, obs.tracks), (ocfg.counts_file, obs.counts)):
            if objs:
                self._append(name, self.obs_files[name],
                             b"".join(dumps(o) + b"\n" for o in objs), len(objs))
        self.tracks += len(obs.tracks)
        if obs.reviews:
            self._write_reviews(obs.reviews)
        if self.outbox is not None and (records := obs.for_modem()):
            try:
                self.outbox.append_many(records)
            except OutboxFull as exc:
                self.refused += len(records)
                self.ratelog.warning("outbox", "outbox refused %d records: %s", len(records),
                                     exc)
