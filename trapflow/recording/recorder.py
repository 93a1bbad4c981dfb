"""Recordings: MCAP files with the ros2 profile that ROS 2 tools and Foxglove read.

Left and right images are sensor_msgs/msg/CompressedImage with the run's rig beside them as
sensor_msgs/msg/CameraInfo and the left-to-right transform on /tf_static (when the rig is
known); pair headers and results are std_msgs/msg/String JSON (one results topic per
algorithm); VO poses are nav_msgs/msg/Odometry, and the trajectory one nav_msgs/msg/Path at
the end; detections and tags are foxglove_msgs/msg/ImageAnnotations on the left image, one
message per pair (with foxglove-schemas-protobuf installed); mono_ir detections are also
vision_msgs/msg/Detection2DArray, one per pair, where that package's definitions are found
on the machine (recording.vision_msgs or ROS 2; else the recording says so once). Every message is
stamped with its pair's capture time; definitions come from recording.msgs. The file is
written as OUT.part and renamed on close, so an interrupted recording never leaves a
half-written OUT behind. Every second the chunk in progress is closed and the file synced,
so a recorder killed by a crash or a power cut loses at most that second: recover() copies
every complete message of the .part into a valid MCAP. record() owns one SUB socket."""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import cv2
import numpy as np
import zmq
from mcap.records import Channel, Header, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import Writer as McapWriter
from mcap_ros2.writer import Writer

from trapflow.calibration.camera import StereoRig
from trapflow.config.schema import DEFAULT_JPEG_QUALITY
from trapflow.errors import ProtocolError, TrapflowError
from trapflow.recording import msgs, vision
from trapflow.wire.messages import StereoPair, to_builtins
from trapflow.wire.tap_msgs import TOPIC_IMAGE, TOPIC_RESULT, TapPair, TapResult, decode_tap
from trapflow.wire.transport import SocketSpec, open_socket

log = logging.getLogger(__name__)

TOPIC_LEFT = "/trapflow/left/image/compressed"
TOPIC_RIGHT = "/trapflow/right/image/compressed"
TOPIC_PAIRS = "/trapflow/pairs"
RESULTS_PREFIX = "/trapflow/results/"
FRAME_LEFT = "trapflow_left"
FRAME_RIGHT = "trapflow_right"
_SEQ_MEMORY = 4096  # pairs whose capture time a late result can still find
_EARLY_MAX = 4096  # result lines held for a pair not yet received
# A chunk is closed (and the file fsynced) at least this often: what a kill -9 can lose.
# Each closed chunk costs a few hundred bytes of index and one fsync; at 1 s, nothing.
FLUSH_INTERVAL_S = 1.0
PART_SUFFIX = ".part"
# How often record() asks whether the pipeline ended, and how long it then waits for the
# last messages its processes published (ipc delivers them at once; this is slack).
ENDED_CHECK_S = 0.5
DRAIN_MS = 300

TOPIC_LEFT_INFO = "/trapflow/left/camera_info"
TOPIC_RIGHT_INFO = "/trapflow/right/camera_info"
TOPIC_TF_STATIC = "/tf_static"
TOPIC_ODOMETRY = "/trapflow/vo/odometry"
TOPIC_PATH = "/trapflow/vo/path"
ANNOTATIONS_PREFIX = "/trapflow/left/annotations/"
ANNOTATED = ("mono_ir", "tags")  # results drawn on the left image in Foxglove
DETECTIONS_PREFIX = "/trapflow/left/detections/"
DETECTED = "mono_ir"  # results written as vision_msgs/Detection2DArray too
VO_ALGO = "stereo_vo"
# rosbag2's record of a reliable, transient-local (latched) publisher, as it writes /tf_static.
_NEVER = "    sec: 2147483647\n    nsec: 4294967295\n"
LATCHED_QOS = ("- history: 3\n  depth: 0\n  reliability: 1\n  durability: 1\n"
               f"  deadline:\n{_NEVER}  lifespan:\n{_NEVER}  liveliness: 1\n"
               f"  liveliness_lease_duration:\n{_NEVER}"
               "  avoid_ros_namespace_conventions: false\n")


class RecorderError(TrapflowError):
    """A recording cannot be written (bad path, disk full) or an input is unusable."""


@dataclass
class RecordCounts:
    """What a recording holds so far."""

    pairs: int = 0
    results: dict[str, int] = field(default_factory=dict)
    malformed: int = 0
    odometry: int = 0  # nav_msgs/Odometry messages: VO results with a pose
    annotations: dict[str, int] = field(default_factory=dict)  # per algorithm: one per pair
    detections: int = 0  # vision_msgs/Detection2DArray messages: one per pair of DETECTED

    @property
    def total_results(self) -> int:
        """All results over all algorithms."""
        return sum(self.results.values())


class Recorder:
    """Writes pairs and results to an MCAP recording; close() finishes and publishes the file."""

    def __init__(self, out: str | Path, rig: StereoRig | None = None,
                 vision_msgs: str = "") -> None:
        self.out = Path(out)
        self.rig = rig  # the run's rig: written as CameraInfo beside each pair's images
        self.part = self.out.with_name(self.out.name + ".part")
        try:
            self._file: IO[bytes] = open(self.part, "wb")  # noqa: SIM115 - closed in close()
        except OSError as exc:
            raise RecorderError(f"cannot write recording {self.out}: {exc.strerror}") from None
        self._writer = Writer(self._file)
        self._schemas: dict[str, Any] = {}
        try:  # Foxglove's ImageAnnotations: only with foxglove-schemas-protobuf installed
            self._annotations_type: str | None = msgs.foxglove_msgdef()[0]
        except ImportError:
            log.info("record: foxglove-schemas-protobuf is not installed; no ImageAnnotations"
                     " (pip install 'trapflow[foxglove]')")
            self._annotations_type = None
        self._defs = {t: msgs.foxglove_msgdef()[1] for t in [self._annotations_type] if t}
        try:  # vision_msgs from the machine (vision_msgs: the config's folder) or nowhere
            found = vision.find(vision_msgs)
            why = f"no vision_msgs definitions found ({vision.WHERE})"
        except ValueError as exc:
            found, why = None, str(exc)
        if found is None:
            log.warning("record: %s; detections are not written as %s (the other topics "
                        "are)", why, vision.DETECTION_ARRAY)
        else:
            self._defs[vision.DETECTION_ARRAY] = found.msgdef
        self._vision = found is not None
        self._seq_time: OrderedDict[int, int] = OrderedDict()
        self._pending: dict[str, tuple[int, list[dict[str, Any]]]] = {}  # algo -> seq, items
        self._early: dict[int, list[tuple[str, str, Any]]] = {}  # results ahead of their pair
        self._early_lines = 0
        self._last_pair = -1  # the highest pair seq recorded
        self._poses: list[tuple[int, list[list[float]]]] = []  # the VO trajectory so far
        self._tf_written = False
        self.counts = RecordCounts()
        self.closed = False
        self._flushed = time.monotonic()

    def _write(self, topic: str, typename: str, msg: dict[str, Any], t: int, seq: int) -> None:
        """Write one message of a ROS 2 type (its definition registered on first use)."""
        schema = self._schemas.get(typename)
        if schema is None:
            text = self._defs.get(typename) or msgs.ros_msgdef(typename)
            schema = self._schemas[typename] = self._writer.register_msgdef(typename, text)
        if topic == TOPIC_TF_STATIC and topic not in self._writer._channel_ids:
            # Latched, as a static transform publisher offers it: rosbag2 keeps the QoS in
            # the channel's metadata, and `ros2 bag play` replays it so late subscribers
            # still get the transform. mcap_ros2 registers channels without metadata.
            self._writer._channel_ids[topic] = self._writer._writer.register_channel(
                topic=topic, message_encoding="cdr", schema_id=schema.id,
                metadata={"offered_qos_profiles": LATCHED_QOS})
        self._writer.write_message(topic, schema, msg, log_time=t, publish_time=t,
                                   sequence=seq if seq >= 0 else 0)

    def add_pair(
        self, header: StereoPair, left: bytes | memoryview, right: bytes | memoryview
    ) -> None:
        """Record one pair; raw BGR payloads are JPEG-encoded first."""
        if header.encoding == "raw":
            left, right = (self._jpeg(header, b) for b in (left, right))
        # The left image is stamped with the pair's capture time, the one its results carry
        # (`timestamp`), so a replay or a `process` of the recording labels every result as
        # the live run did; the right keeps its skew from the left. (Carried from each eye's
        # own monotonic time, the stamps were 1-58 ms off the live results', issue 32.)
        t_left = header.t_wall_ns
        t_right = header.t_wall_ns + (header.t_right_ns - header.t_left_ns)
        for topic, frame_id, t, data in (
            (TOPIC_LEFT, FRAME_LEFT, t_left, left), (TOPIC_RIGHT, FRAME_RIGHT, t_right, right)
        ):
            msg = {"header": {"stamp": msgs.stamp(t), "frame_id": frame_id},
                   "format": "jpeg", "data": bytes(data)}
            self._write(topic, "sensor_msgs/msg/CompressedImage", msg, t, header.seq)
        if self.rig is not None and self.rig.size == (header.width, header.height):
            if not self._tf_written:  # once, as a static transform publisher latches it
                self._tf_written = True
                self._write(TOPIC_TF_STATIC, "tf2_msgs/msg/TFMessage",
                            msgs.tf_static(self.rig, t_left, FRAME_LEFT, FRAME_RIGHT),
                            t_left, header.seq)
            self._camera_info(header.seq, t_left, t_right)
        meta = json.dumps(to_builtins(header), separators=(",", ":"))
        self._write(TOPIC_PAIRS, "std_msgs/msg/String", {"data": meta}, t_left, header.seq)
        self._seq_time[header.seq] = t_left
        if len(self._seq_time) > _SEQ_MEMORY:
            self._seq_time.popitem(last=False)
        self._last_pair = max(self._last_pair, header.seq)
        self.counts.pairs += 1
        if self._early:
            self._release_early(header.seq)
        self.maybe_flush()

    def maybe_flush(self) -> None:
        """Close the chunk in progress and sync the file when the flush interval has passed."""
        if self.closed or time.monotonic() - self._flushed < FLUSH_INTERVAL_S:
            return
        self._flushed = time.monotonic()
        # mcap_ros2's Writer has no flush of its own; its mcap Writer's ends the chunk in
        # progress and writes it out. Measured with kill -9 at 10 pairs/s of 160x120: without
        # it up to a 1 MB chunk is lost (about 5 s; 27 of 80 pairs in one run), with it < 1 s.
        self._writer._writer.flush()  # type: ignore[no-untyped-call]
        os.fsync(self._file.fileno())

    def _camera_info(self, seq: int, t_left: int, t_right: int) -> None:
        """The rectified rig as a left/right CameraInfo pair, as camera_calibration writes it
        (the right P carries -fx * baseline): what replay reads the rig back from."""
        assert self.rig is not None
        r = self.rig
        for topic, frame_id, t, right in ((TOPIC_LEFT_INFO, FRAME_LEFT, t_left, False),
                                          (TOPIC_RIGHT_INFO, FRAME_RIGHT, t_right, True)):
            msg = {"header": {"stamp": msgs.stamp(t), "frame_id": frame_id}, "height": r.height,
                   "width": r.width, "distortion_model": "plumb_bob", "d": [0.0] * 5,
                   "k": [float(v) for v in r.K.ravel()], "r": [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
                   "p": [float(v) for v in r.projection(right).ravel()], "binning_x": 0,
                   "binning_y": 0, "roi": {"x_offset": 0, "y_offset": 0, "height": 0,
                                           "width": 0, "do_rectify": False}}
            self._write(topic, "sensor_msgs/msg/CameraInfo", msg, t, seq)

    @staticmethod
    def _jpeg(header: StereoPair, data: bytes | memoryview) -> bytes:
        img = np.frombuffer(data, dtype=np.uint8).reshape(header.height, header.width, 3)
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, DEFAULT_JPEG_QUALITY])
        if not ok:
            raise RecorderError(f"pair {header.seq}: JPEG encoding failed")
        return bytes(buf.tobytes())

    def add_result(self, line: str | bytes) -> None:
        """Record one normalized result line `{"<algorithm>": {..., "seq": N}}`."""
        text = line.decode("utf-8") if isinstance(line, bytes) else line
        try:
            obj: Any = json.loads(text)
        except ValueError as exc:
            raise RecorderError(
                f"result: expected one JSON object, got {text[:60]!r}: {exc}"
            ) from None
        if not isinstance(obj, dict) or len(obj) != 1:
            raise RecorderError(
                f"result: expected one {{algorithm: {{...}}}} object, got {text[:60]!r}"
            )
        (algo, body), = obj.items()
        if not isinstance(algo, str) or not algo.isidentifier():
            raise RecorderError(f"result: expected an algorithm name as key, got {algo!r}")
        seq = body.get("seq") if isinstance(body, dict) else None
        seq = seq if isinstance(seq, int) and seq >= 0 else -1
        if seq > self._last_pair and seq not in self._seq_time:
            # Its pair is still on the way: the big image frames come through their own
            # tap connection and fall behind the results under load. The result waits for
            # its pair's capture time (Foxglove draws annotations on the image with the
            # same stamp; a receive time would also sort it after later results).
            self._early.setdefault(seq, []).append((text, algo, body))
            self._early_lines += 1
            if self._early_lines > _EARLY_MAX:
                self._release_early(min(self._early))
            return
        self._emit(text, algo, body, seq, self._seq_time.get(seq) or _stamp_of(body))

    def _emit(self, text: str, algo: str, body: Any, seq: int, t: int) -> None:
        self._write(RESULTS_PREFIX + algo, "std_msgs/msg/String", {"data": text.strip()},
                    t, seq)
        self.counts.results[algo] = self.counts.results.get(algo, 0) + 1
        if isinstance(body, dict):
            self._derived(algo, body, seq, t)
        self.maybe_flush()

    def _release_early(self, upto: int) -> None:
        """Write the held results of every pair up to seq `upto`, in order: with their
        pair's capture time, or the time in the result when the tap dropped the pair."""
        for seq in sorted(s for s in self._early if s <= upto):
            for text, algo, body in self._early.pop(seq):
                self._early_lines -= 1
                self._emit(text, algo, body, seq, self._seq_time.get(seq) or _stamp_of(body))

    def _derived(self, algo: str, body: dict[str, Any], seq: int, t: int) -> None:
        """The typed messages a result line adds: VO odometry, and image annotations (one
        message per pair: the lines of one pair's result come one after the other)."""
        if algo == VO_ALGO and body.get("ok") and _is_pose(body.get("pose")):
            self._poses.append((t, body["pose"]))
            self._write(TOPIC_ODOMETRY, "nav_msgs/msg/Odometry",
                        msgs.odometry(body["pose"], t, FRAME_LEFT), t, seq)
            self.counts.odometry += 1
        if algo in ANNOTATED and (self._annotations_type is not None
                                  or (algo == DETECTED and self._vision)):
            pending = self._pending.get(algo)
            if pending is not None and pending[0] != seq:
                self._annotate(algo)
            self._pending.setdefault(algo, (seq, []))[1].append(body)

    def _annotate(self, algo: str) -> None:
        seq, items = self._pending.pop(algo)
        t = self._seq_time.get(seq) or _stamp_of(items[0])
        if self._annotations_type is not None:
            self._write(ANNOTATIONS_PREFIX + algo, self._annotations_type,
                        msgs.image_annotations(algo, items, t), t, seq)
            self.counts.annotations[algo] = self.counts.annotations.get(algo, 0) + 1
        if algo == DETECTED and self._vision:
            self._write(DETECTIONS_PREFIX + algo, vision.DETECTION_ARRAY,
                        vision.detection_array(items, t, FRAME_LEFT), t, seq)
            self.counts.detections += 1

    def close(self) -> None:
        """Write the MCAP summary and footer, then move OUT.part to OUT. Idempotent."""
        if self.closed:
            return
        self.closed = True
        try:
            if self._early:
                self._release_early(max(self._early))
            for algo in list(self._pending):
                self._annotate(algo)
            if self._poses:  # the whole trajectory once, stamped with its last pose
                t_last = self._poses[-1][0]
                self._write(TOPIC_PATH, "nav_msgs/msg/Path", msgs.path(self._poses), t_last, 0)
            self._writer.finish()  # type: ignore[no-untyped-call]
        finally:
            self._file.close()
        self.part.replace(self.out)

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _stamp_of(body: Any) -> int:
    """A result's own capture time (its `timestamp`, UTC to the millisecond) in ns, for a
    result whose pair the recording does not have; the receive time if it has none."""
    stamp = body.get("timestamp") if isinstance(body, dict) else None
    if isinstance(stamp, str):
        try:
            when = dt.datetime.strptime(stamp, "%Y-%m-%d %H:%M:%S.%f")
        except ValueError:
            pass
        else:
            return int(when.replace(tzinfo=dt.timezone.utc).timestamp() * 1000) * 1_000_000
    return time.time_ns()


def _is_pose(value: object) -> bool:
    return (isinstance(value, list) and len(value) == 3
            and all(isinstance(r, list) and len(r) == 4 for r in value))


def record(endpoint: str | Sequence[str], out: str | Path, stop: threading.Event,
           counts: RecordCounts | None = None, poll_ms: int = 100,
           rig: StereoRig | None = None, duration_s: float | None = None,
           ended: Callable[[], bool] | None = None, vision_msgs: str = "") -> RecordCounts:
    """Attach to the tap(s) at endpoint and record image pairs and results until stop is set.

    A pipeline publishes pairs on the broker's tap and results on the normalizer's: pass
    both (Endpoints.tap and Endpoints.results_tap) to record both.

    counts (optional) is updated live so a caller can watch progress; it is also returned.
    rig (the pipeline's, from its status) is written as CameraInfo beside the images;
    vision_msgs names a folder of vision_msgs definitions (recording.vision_msgs).
    Malformed tap messages are counted and skipped. It ends at stop, after duration_s, or
    once ended() holds (the pipeline is gone: checked every ENDED_CHECK_S), when what its
    processes published last has been written. The file is closed cleanly however the loop
    ends (stop, Ctrl-C, an error).
    """
    rec = Recorder(out, rig, vision_msgs)
    if counts is not None:
        rec.counts = counts
    ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context.instance()
    first, *more = [endpoint] if isinstance(endpoint, str) else endpoint
    try:
        sub = open_socket(ctx, SocketSpec(zmq.SUB, first, rcvhwm=1000, also_connect=tuple(more),
                                          subscribe=(TOPIC_IMAGE, TOPIC_RESULT)))
    except BaseException:
        rec.close()
        raise
    now = time.monotonic()
    until = now + duration_s if duration_s is not None else None
    next_check = now + ENDED_CHECK_S
    try:
        while not stop.is_set():
            now = time.monotonic()
            if until is not None and now >= until:
                log.info("record: duration of %g s reached", duration_s)
                break
            if ended is not None and now >= next_check:
                next_check = now + ENDED_CHECK_S
                if ended():  # its processes are gone: what they sent is queued here
                    while sub.poll(DRAIN_MS):
                        _take(rec, sub)
                    log.info("record: the pipeline ended")
                    break
            if not sub.poll(poll_ms):
                rec.maybe_flush()  # a quiet pipeline: what came last is on disk all the same
                continue
            _take(rec, sub)
    finally:
        sub.close(linger=0)
        rec.close()
    log.info("record: %d pairs, %d results in %s", rec.counts.pairs, rec.counts.total_results, out)
    return rec.counts


def _take(rec: Recorder, sub: zmq.Socket[bytes]) -> None:
    """One tap message into the recording; a malformed one counted and skipped."""
    frames = sub.recv_multipart(copy=False)
    try:
        msg = decode_tap(frames)
        if isinstance(msg, TapPair):
            rec.add_pair(msg.header, msg.left, msg.right)
        elif isinstance(msg, TapResult):
            rec.add_result(msg.line)
    except (ProtocolError, RecorderError) as exc:
        if rec.counts.malformed == 0:
            log.warning("record: skipping malformed tap message: %s", exc)
        rec.counts.malformed += 1


def recovered_name(part: Path) -> Path:
    """Where recover() writes by default: the name the recording was meant to have."""
    name = part.name
    return part.with_name(name[: -len(PART_SUFFIX)] if name.endswith(PART_SUFFIX)
                          else f"{part.stem}.recovered{part.suffix or '.mcap'}")


def recover(part: str | Path, out: str | Path) -> int:
    """Copy every complete message of a cut recording (OUT.part of a killed recorder, or an
    MCAP without its summary) into a valid MCAP at out; returns how many were copied.

    The cut file is read as a stream up to its first incomplete or damaged record (a chunk
    is checked against its CRC); schemas, channels and messages are copied byte for byte.
    """
    part, out = Path(part), Path(out)
    if out.resolve() == part.resolve():
        raise RecorderError(f"recover: output {out} is the input; name another file")
    try:
        src: IO[bytes] = open(part, "rb")  # noqa: SIM115 - closed below
    except OSError as exc:
        raise RecorderError(f"recover: cannot read {part}: {exc.strerror}") from None
    # Not OUT.part: that is the input itself when it is recovered under its intended name.
    tmp = out.with_name(out.name + ".recovering")
    try:
        copied = _copy_complete(part, src, tmp)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    tmp.replace(out)
    return copied


def _copy_complete(part: Path, src: IO[bytes], tmp: Path) -> int:
    copied = 0
    schemas: dict[int, int] = {}
    channels: dict[int, int] = {}
    with src, open(tmp, "wb") as dst:
        writer = McapWriter(dst)
        started = False
        try:
            for record in StreamReader(src, validate_crcs=True).records:
                if isinstance(record, Header):
                    writer.start(profile=record.profile, library=record.library)
                    started = True
                elif not started:
                    raise RecorderError(f"recover: {part} does not start with an MCAP header")
                elif isinstance(record, Schema):
                    schemas[record.id] = writer.register_schema(record.name, record.encoding,
                                                                record.data)
                elif isinstance(record, Channel):
                    channels[record.id] = writer.register_channel(
                        record.topic, record.message_encoding,
                        schemas.get(record.schema_id, 0), record.metadata)
                elif isinstance(record, Message) and record.channel_id in channels:
                    writer.add_message(channels[record.channel_id], record.log_time,
                                       record.data, record.publish_time, record.sequence)
                    copied += 1
        except RecorderError:
            raise
        except Exception as exc:  # noqa: BLE001 - the cut: short read, half chunk, bad CRC
            log.info("recover: %s ends after %d complete messages (%s: %s)",
                     part, copied, type(exc).__name__, exc)
        if not started:
            raise RecorderError(f"recover: {part} is not an MCAP recording (no header)")
        writer.finish()  # type: ignore[no-untyped-call]
    return copied
