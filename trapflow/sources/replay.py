"""Replay of recordings: trapflow MCAP files and ROS 2 bags (sqlite3 or MCAP) through rosbags.

Images come from two sensor_msgs Image/CompressedImage topics (or one custom stereo message
whose .msg definition the user gives), are paired by timestamp, and are delivered with the
original timing scaled by `rate` (0: as fast as possible), each pair labelled with its
recorded capture time.

source.options: rate (1.0), left_topic, right_topic, tolerance_s (half the frame period),
msg_type + msg_def (path of a .msg file) + topic, left_field ('left'), right_field ('right'),
left_info_topic, right_info_topic (CameraInfo giving the rig; found beside the image topics).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Connection
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from trapflow.calibration.camera import StereoRig
from trapflow.config.schema import SourceConfig
from trapflow.sources.base import Frames, Geometry, SkipPair, Source, SourceError
from trapflow.sources.decode import decode_bgr, same_size
from trapflow.sources.sync import SkewStats, StereoSync

log = logging.getLogger(__name__)

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (IMAGE, COMPRESSED)
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
# (t_left, left, t_right, right); each image is (message index, message, or why it is unusable)
Pair = tuple[int, "Msg", int, "Msg"]
Msg = tuple[int, Any]

# ROS image encodings -> (channels, OpenCV conversion to BGR or None)
_ENCODINGS: dict[str, tuple[int, int | None]] = {
    "bgr8": (3, None), "8UC3": (3, None), "rgb8": (3, cv2.COLOR_RGB2BGR),
    "mono8": (1, cv2.COLOR_GRAY2BGR), "8UC1": (1, cv2.COLOR_GRAY2BGR),
    "bgra8": (4, cv2.COLOR_BGRA2BGR), "rgba8": (4, cv2.COLOR_RGBA2BGR),
}


class Undecodable:
    """A bag message that could not be deserialized: it still pairs, then is skipped."""

    def __init__(self, reason: str) -> None:
        self.reason = reason


def image_to_bgr(msg: Any, where: str = "replay") -> np.ndarray:
    """A sensor_msgs Image or CompressedImage as a BGR uint8 array; SkipPair if unusable."""
    if isinstance(msg, Undecodable):
        raise SkipPair("undecodable", f"{where}: {msg.reason}")
    if hasattr(msg, "format"):  # CompressedImage
        return decode_bgr(bytes(msg.data), f"{where}: CompressedImage ({msg.format!r})")
    enc = str(msg.encoding)
    if enc == "mono16" or enc == "16UC1":
        raw16 = np.frombuffer(bytes(msg.data), dtype=">u2" if msg.is_bigendian else "<u2")
        try:
            rows16 = raw16.reshape(msg.height, msg.step // 2)[:, : msg.width]
        except ValueError:
            raise SkipPair("undecodable", f"{where}: {enc} Image of {raw16.size * 2} bytes "
                                          f"does not fit {msg.height} rows of {msg.step}") from None
        return cv2.cvtColor((rows16 >> 8).astype(np.uint8), cv2.COLOR_GRAY2BGR)
    if enc not in _ENCODINGS:
        raise SkipPair("undecodable", f"{where}: Image encoding {enc!r} unsupported; expected "
                                      f"one of {', '.join([*_ENCODINGS, 'mono16'])}")
    ch, conv = _ENCODINGS[enc]
    raw = np.frombuffer(bytes(msg.data), np.uint8)
    try:
        rows = raw.reshape(msg.height, msg.step)[:, : msg.width * ch]
    except ValueError:
        raise SkipPair("undecodable", f"{where}: Image of {raw.size} bytes does not fit "
                                      f"{msg.height} rows of {msg.step}") from None
    img = rows.reshape(msg.height, msg.width, ch)
    return np.ascontiguousarray(img) if conv is None else cv2.cvtColor(img, conv)


def stamp_ns(msg: Any, fallback: int) -> int:
    """The message header stamp in ns, or the bag time when the stamp is unset."""
    header = getattr(msg, "header", None)
    if header is None:
        return fallback
    t = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    return t if t > 0 else fallback


def _pick_topics(conns: list[Connection], left: str | None, right: str | None) -> tuple[str, str]:
    images = sorted({c.topic for c in conns if c.msgtype in IMAGE_TYPES})
    found = ", ".join(f"{c.topic} ({c.msgtype})" for c in conns) or "nothing"
    if left or right:
        for name in (left, right):
            if name not in images:
                raise SourceError(f"replay: image topic {name!r} not in the bag; it has {found}")
        assert left and right
        return left, right
    if not images:
        raise SourceError(f"replay: the bag has no image topics (Image or CompressedImage); "
                          f"it has {found}")
    lefts = [t for t in images if "left" in t.lower()]
    rights = [t for t in images if "right" in t.lower()]
    if len(lefts) == 1 and len(rights) == 1:
        return lefts[0], rights[0]
    if len(images) == 2:  # e.g. /cam0 and /cam1: the first name is the left camera
        return images[0], images[1]
    raise SourceError(f"replay: cannot tell left from right among {', '.join(images)}; "
                      "set source.options left_topic and right_topic")


def _namespace(topic: str) -> str:
    return topic.rsplit("/", 1)[0]


def _info_topic(infos: list[str], image: str, side: str) -> str | None:
    """The CameraInfo topic beside an image topic (same namespace), else the one named `side`."""
    ns = _namespace(image)
    while ns:
        near = [t for t in infos if t.startswith(ns + "/")]
        if len(near) == 1:
            return near[0]
        ns = _namespace(ns)
    named = [t for t in infos if side in t.lower()]
    return named[0] if len(named) == 1 else None


def rig_from_camera_info(
    left: Any, right: Any, fallback_baseline_m: float
) -> tuple[StereoRig, str]:
    """The rectified rig of a left/right CameraInfo pair: intrinsics from the left P (K when
    P is unset), baseline -P_right[0,3] / P_right[0,0]; and a note when the baseline is not
    in the messages (a monocular P), so the configured one is used."""
    p = [float(v) for v in left.p]
    k = [float(v) for v in left.k]
    fx, fy, cx, cy = (p[0], p[5], p[2], p[6]) if p[0] > 0 else (k[0], k[4], k[2], k[5])
    pr = [float(v) for v in right.p]
    note = ""
    if pr[0] > 0 and -pr[3] / pr[0] > 0:
        baseline = -pr[3] / pr[0]
    else:
        baseline, note = fallback_baseline_m, ", baseline from rig.baseline_m"
    rig = StereoRig(width=int(left.width), height=int(left.height), fx=fx, fy=fy, cx=cx, cy=cy,
                    baseline_m=baseline)
    return rig, note


class ReplaySource(Source):
    """`replay:PATH`: a recording fed back with its original timing."""

    paced = True

    def __init__(self, cfg: SourceConfig, rig: StereoRig) -> None:
        super().__init__(rig)
        self.cfg = cfg
        self.path = Path(cfg.uri)
        self.loop = cfg.loop
        self.finite = not cfg.loop
        opts = cfg.options
        self.rate = float(opts.get("rate", 1.0))
        if self.rate < 0:
            raise SourceError(
                f"replay: rate must be >= 0 (0 = as fast as possible), got {self.rate}"
            )
        self.opts = opts
        self.pairs_read = 0
        self.skew = SkewStats()
        self._reader: AnyReader | None = None
        self._it: Iterator[Pair] | None = None
        self._t_first: int | None = None
        self._mono_first = 0
        self._lap_offset = 0
        self._t_last = 0

    # -- geometry -----------------------------------------------------------------

    def geometry(self) -> Geometry:
        """The first left image's size, and the rig of the bag's CameraInfo pair if it has one."""
        self.open()
        try:
            msg_type = self.opts.get("msg_type")
            if not msg_type:
                return self._geometry()
            first = next(self._custom_pairs(str(msg_type)), None)  # one stereo message
            if first is None:
                return Geometry()
            img = image_to_bgr(first[1][1])
            return Geometry(size=(img.shape[1], img.shape[0]), where=f"{msg_type} in {self.path}")
        finally:
            self.close()

    def _geometry(self) -> Geometry:
        reader = self._reader
        assert reader is not None
        conns = reader.connections
        lt, rt = _pick_topics(conns, self.opts.get("left_topic"), self.opts.get("right_topic"))
        where = f"{lt} and {rt} in {self.path}"
        first = next(reader.messages(connections=[c for c in conns if c.topic == lt]), None)
        if first is None:
            return Geometry(where=where)
        img = image_to_bgr(reader.deserialize(first[2], first[0].msgtype))
        size = (img.shape[1], img.shape[0])
        infos = sorted({c.topic for c in conns if c.msgtype == CAMERA_INFO})
        topics = (self.opts.get("left_info_topic") or _info_topic(infos, lt, "left"),
                  self.opts.get("right_info_topic") or _info_topic(infos, rt, "right"))
        if not infos or None in topics or topics[0] == topics[1]:
            if infos:
                log.warning("replay: cannot tell which of %s belongs to %s and %s; set "
                            "source.options left_info_topic and right_info_topic",
                            ", ".join(infos), lt, rt)
            return Geometry(size=size, where=where)
        msgs = []
        for topic in topics:
            found = next(reader.messages(connections=[c for c in conns if c.topic == topic]),
                         None)
            if found is None:
                return Geometry(size=size, where=where)
            msgs.append(reader.deserialize(found[2], found[0].msgtype))
        rig, note = rig_from_camera_info(msgs[0], msgs[1], self.rig.baseline_m)
        if rig.size != size:
            log.warning("replay: %s says %dx%d, but the images are %dx%d; CameraInfo ignored",
                        topics[0], rig.width, rig.height, *size)
            return Geometry(size=size, where=where)
        return Geometry(size=size, rig=rig, where=where,
                        origin=f"CameraInfo {topics[0]}, {topics[1]} in {self.path}{note}")

    # -- opening and pairing -------------------------------------------------------

    def open(self) -> None:
        if not self.path.exists():
            raise SourceError(f"replay: recording not found: {self.path}")
        try:
            self._reader = AnyReader([self.path],
                                     default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            self._reader.open()
        except Exception as exc:  # noqa: BLE001 - rosbags raises many types for a bad file
            self._reader = None
            cut = self.path.name.endswith(".part") or "magic" in str(exc)
            hint = (f"; it looks cut short (a recorder killed mid-run): `trapflow recover "
                    f"{self.path}` keeps its complete messages" if cut else "")
            raise SourceError(f"replay: cannot read {self.path} as a ROS 2 bag or MCAP "
                              f"recording: {exc}{hint}") from None
        self._register_custom()
        self._it = self._pairs()
        self._mono_first = time.monotonic_ns()

    def _register_custom(self) -> None:
        assert self._reader is not None
        msg_type = self.opts.get("msg_type")
        if not msg_type:
            return
        def_path = self.opts.get("msg_def")
        if def_path:
            try:
                text = Path(str(def_path)).read_text(encoding="utf-8")
                self._reader.typestore.register(get_types_from_msg(text, str(msg_type)))
            except OSError as exc:
                raise SourceError(
                    f"replay: cannot read msg_def {def_path}: {exc.strerror}"
                ) from None
            except Exception as exc:  # noqa: BLE001 - parse errors of the user's .msg
                raise SourceError(f"replay: msg_def {def_path} for {msg_type}: {exc}") from None

    def _tolerance(self, conns: list[Connection]) -> int:
        if "tolerance_s" in self.opts:
            return int(float(self.opts["tolerance_s"]) * 1e9)
        assert self._reader is not None
        n = max(c.msgcount for c in conns)
        dur = self._reader.duration
        period = dur / (n - 1) if n > 1 and dur > 0 else 1e9 / self.cfg.rate_hz
        return int(period / 2)

    def _pairs(self) -> Iterator[Pair]:
        """Matched (t_left, left msg, t_right, right msg) in time order, images not decoded."""
        reader = self._reader
        assert reader is not None
        msg_type = self.opts.get("msg_type")
        if msg_type:
            yield from self._custom_pairs(str(msg_type))
            return
        lt, rt = _pick_topics(reader.connections, self.opts.get("left_topic"),
                              self.opts.get("right_topic"))
        conns = [c for c in reader.connections if c.topic in (lt, rt)]
        sync: StereoSync[Msg] = StereoSync(self._tolerance(conns), max_pending=64)
        sync.stats = self.skew
        for index, (conn, t_bag, raw) in enumerate(self._messages(conns)):
            msg = self._deserialize(raw, conn, index)
            t = stamp_ns(msg, t_bag)
            (sync.push_left if conn.topic == lt else sync.push_right)(t, (index, msg))
            while (pair := sync.pop()) is not None:
                yield pair
        sync.flush()

    def _custom_pairs(self, msg_type: str) -> Iterator[Pair]:
        reader = self._reader
        assert reader is not None
        topic = self.opts.get("topic")
        conns = [c for c in reader.connections
                 if c.msgtype == msg_type and (not topic or c.topic == topic)]
        if not conns:
            raise SourceError(f"replay: no topic of type {msg_type} in {self.path}")
        lf = str(self.opts.get("left_field", "left"))
        rf = str(self.opts.get("right_field", "right"))
        for index, (conn, t_bag, raw) in enumerate(self._messages(conns)):
            msg = self._deserialize(raw, conn, index)
            if isinstance(msg, Undecodable):
                yield t_bag, (index, msg), t_bag, (index, msg)
                continue
            try:
                left, right = getattr(msg, lf), getattr(msg, rf)
            except AttributeError:
                raise SourceError(f"replay: {msg_type} has no fields {lf!r} and {rf!r}") from None
            tl, tr = stamp_ns(left, stamp_ns(msg, t_bag)), stamp_ns(right, stamp_ns(msg, t_bag))
            self.skew.add(tl - tr)
            yield tl, (index, left), tr, (index, right)

    def _messages(self, conns: list[Connection]) -> Iterator[tuple[Connection, int, bytes]]:
        """The raw messages; a recording damaged mid-file (a chunk that fails its checksum)
        ends with a SourceError naming where: nothing after it can be trusted in order."""
        assert self._reader is not None
        index = 0
        try:
            for item in self._reader.messages(connections=conns):
                yield item
                index += 1
        except Exception as exc:  # noqa: BLE001 - rosbags raises many types for a damaged file
            raise SourceError(f"replay: {self.path} is damaged after message {index}: "
                              f"{type(exc).__name__}: {exc}") from None

    def _deserialize(self, raw: bytes, conn: Connection, index: int) -> Any:
        """The message, or Undecodable with the reason (the pair is skipped, the bag goes on)."""
        assert self._reader is not None
        try:
            return self._reader.deserialize(raw, conn.msgtype)
        except Exception as exc:  # noqa: BLE001 - rosbags raises many types for bad bytes
            return Undecodable(f"message {index} on {conn.topic} ({conn.msgtype}, "
                               f"{len(raw)} bytes) does not decode: {type(exc).__name__}: {exc}")

    # -- delivery -----------------------------------------------------------------

    def _next_pair(self) -> Pair | None:
        assert self._it is not None
        pair = next(self._it, None)
        if pair is None and self.loop and self.pairs_read > 0:
            assert self._t_first is not None
            self._lap_offset += self._t_last - self._t_first + 1  # next lap starts right after
            self._t_first = None
            self._it = self._pairs()
            pair = next(self._it, None)
        return pair

    def read(self) -> Frames | None:
        if self._it is None:
            raise SourceError("replay: read() before open()")
        pair = self._next_pair()
        if pair is None:
            return None
        tl, lmsg, tr, rmsg = pair
        if self._t_first is None:
            self._t_first = tl
            if self.pairs_read == 0:
                self._mono_first = time.monotonic_ns()
        self._t_last = tl
        if self.rate > 0:
            due = self._mono_first + int((self._lap_offset + tl - self._t_first) / self.rate)
            delay = due - time.monotonic_ns()
            if delay > 0:
                time.sleep(delay / 1e9)
        # Stamped when due, before decoding: a slow (cold) first decode must not shift the
        # first stamp against the later ones.
        now = time.monotonic_ns()
        self.pairs_read += 1  # counted read whether or not it decodes: it is one pair
        (il, lm), (ir, rm) = lmsg, rmsg
        left = image_to_bgr(lm, f"replay: {self.path.name} message {il}")
        right = image_to_bgr(rm, f"replay: {self.path.name} message {ir}")
        same_size(left, right, f"replay: {self.path.name} messages {il} and {ir}")
        # The recorded left stamp is the pair's capture time (a later lap of a loop goes on
        # past the last one), whatever the replay's pace.
        return Frames(left=left, right=right, t_left_ns=now, t_right_ns=now + (tr - tl),
                      t_wall_ns=self._lap_offset + tl)

    def count_pairs(self) -> int:
        """How many pairs one pass over the recording yields (opens and closes it)."""
        self.open()
        try:
            return sum(1 for _ in self._pairs())
        finally:
            self.close()

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None
        self._it = None
