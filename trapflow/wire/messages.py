"""The only module that knows the byte format of what travels between processes.

Every message is a msgspec Struct encoded with msgpack; image payloads travel in
their own frames (sent with copy=False) so nothing large is ever re-serialised.
Decoding never trusts the wire: every decoder raises ProtocolError with a reason.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated, Any, Literal, Union

import msgspec

from trapflow.errors import ProtocolError

# Upper bounds that make a hostile or corrupt peer harmless.
MAX_HEADER_BYTES = 4096
MAX_RESULT_BYTES = 1 << 20
MAX_SIDE = 8192
ENCODINGS = ("jpeg", "raw")

Buffer = Union[bytes, memoryview, Any]  # zmq.Frame or bytes-like


class Msg(msgspec.Struct, frozen=True, kw_only=True, omit_defaults=True):
    """Base of every message: frozen, keyword-only, compact on the wire."""


# --- frames: capture -> broker -> workers ------------------------------------


class StereoPair(Msg, frozen=True, tag="pair"):
    """Header of one stereo pair; frames 1 and 2 carry the left and right image."""

    seq: int
    t_wall_ns: int  # wall clock at capture, a label only
    t_mono_ns: int  # monotonic clock at capture, for latency and ordering
    t_left_ns: int
    t_right_ns: int
    skew_ns: int
    encoding: Literal["jpeg", "raw"]
    width: int
    height: int
    source: str = "synthetic"
    motion: bool | None = None  # what the motion gate saw in the left image (None: no gate)
    motion_score: float = 0.0  # share of the gate's small image that moved
    motion_regions: tuple[tuple[int, int, int, int], ...] = ()  # x1 y1 x2 y2 px, largest first
    # True: t_wall_ns is the source's own capture time (a recording's stamps), and durations
    # are measured on it, as recorded (a replay at any pace); False: on t_mono_ns.
    source_time: bool = False


class Job(Msg, frozen=True, tag="job"):
    """Broker -> worker: a pair to process. gap counts pairs skipped since the last job."""

    pool: str
    gap: int = 0


# --- results ------------------------------------------------------------------


class Detection(Msg, frozen=True):
    """One detected object: label, confidence and box x1, y1, x2, y2 in pixels; where the
    stereo pair measured it, its range, position and length with their uncertainties (all
    metres, left camera frame), else why not (`unmeasured`, a reason code)."""

    label: str
    confidence: float
    box: tuple[float, float, float, float]
    range_m: float | None = None
    range_sd_m: float | None = None
    xyz: tuple[float, float, float] | None = None
    disparity_px: float | None = None
    length_m: float | None = None
    length_sd_m: float | None = None
    length_method: str = ""  # "endpoints" (two ends along the major axis) or "box"
    unmeasured: str = ""  # out_of_view, textureless, ambiguous, low_score, bad_box, ...


class BoxView(Msg, frozen=True):
    """A small JPEG crop of one detection's box, cut from the pair's left image by the
    worker while it holds the pixels (trapflow.pools.pair_path.crop_views): the review
    queue's best view of a track. `box` is the detection's box as the result has it (the
    normalizer matches them by it); never written to results.jsonl."""

    box: tuple[float, float, float, float]
    jpeg: bytes
    sharpness: float  # variance of the Laplacian (trapflow.tracking.review.sharpness)


class MonoIR(Msg, frozen=True, tag="mono_ir"):
    """Mono image recognition: the detections in the left image."""

    detections: list[Detection] = []
    model: str = ""  # short hash of the ONNX model that found them (onnx_session.model_hash)
    views: list[BoxView] = []  # crops of its confident boxes, for the review queue


class StereoIR(Msg, frozen=True, tag="stereo_ir"):
    """Stereo image recognition: one label for the pair."""

    label: str
    confidence: float
    calib: str = ""  # id of the stereo rig the pair was taken with (StereoRig.id)
    model: str = ""  # short hash of the ONNX model that classified it


class StereoVO(Msg, frozen=True, tag="stereo_vo"):
    """Stereo visual odometry: motion since the previous pair as [R|t], and the pose."""

    ok: bool
    rotation: tuple[float, ...] = ()  # 3x3, row major
    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    pose: tuple[float, ...] = ()  # accumulated 3x4 [R|t], row major
    inliers: int = 0
    reinit: bool = False
    calib: str = ""  # id of the rig VO computed with (StereoRig.id)


class Tag(Msg, frozen=True):
    """One AprilTag: id, corners in pixels, pose (rotation 3x3 row major, translation)."""

    id: int
    corners: list[tuple[float, float]]
    rotation: tuple[float, ...] = ()
    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    error: float = 0.0


class Tags(Msg, frozen=True, tag="tags"):
    """AprilTag detection with pose."""

    tags: list[Tag] = []
    calib: str = ""  # id of the rig the poses were computed with (StereoRig.id)


class Extra(Msg, frozen=True, tag="extra"):
    """Result of a third-party algorithm: a name and flat JSON-able fields."""

    name: str
    fields: dict[str, Any] = {}


Body = Union[MonoIR, StereoIR, StereoVO, Tags, Extra]


class Result(Msg, frozen=True, tag="result"):
    """Envelope of every result: which pair, which worker, how long it took."""

    seq: int
    t_wall_ns: int
    t_mono_ns: int
    pool: str
    worker: str
    proc_ns: int
    body: Body
    source_time: bool = False  # as the pair's (StereoPair.source_time)

    def capture_ns(self) -> int:
        """The pair's capture time on the clock durations are measured on (a track's age
        and gaps, a counting interval's length): the monotonic clock at capture, or a
        recording's own stamps. Never the wall clock of a live run, which an NTP fix steps;
        t_wall_ns stays the pair's label."""
        return self.t_wall_ns if self.source_time else self.t_mono_ns


# --- ground truth (synthetic sources only; never shown to algorithms) -------------


class TruthObject(Msg, frozen=True):
    """One animal or tag in the left image: label, box x1 y1 x2 y2 in pixels, depth in m."""

    label: str
    box: tuple[float, float, float, float]
    depth_m: float = 0.0
    id: int = -1  # track id of the animal, or the AprilTag id
    occluded: float = 0.0  # fraction hidden
    length_m: float = 0.0  # an animal's greatest body extent (legs and claws included); 0: unset
    xyz: tuple[float, float, float] | None = None  # its centre in the left camera frame, m


class Truth(Msg, frozen=True, tag="truth"):
    """What a synthetic pair really shows: left-camera pose (3x4 world<-camera), objects."""

    seq: int
    pose: tuple[float, ...]  # 3x4 [R|t], row major, camera-to-world
    objects: list[TruthObject] = []
    scene_label: str = "empty"


# --- worker -> broker ---------------------------------------------------------


class Ready(Msg, frozen=True, tag="ready"):
    """A worker can take `credit` more jobs."""

    worker: str
    pool: str
    credit: int = 1


class Heartbeat(Msg, frozen=True, tag="heartbeat"):
    """A node is alive; state is its lifecycle state, reason why it is not active."""

    node: str
    pid: int
    state: str
    reason: str = ""
    counters: dict[str, int] = {}


# Capture's heartbeat counters failed_<kind>: pairs skipped at capture, by kind.
FAILED_PREFIX = "failed_"


class CaptureCounters(msgspec.Struct, frozen=True, kw_only=True):
    """What capture tells the supervisor with every heartbeat (as flat counters on the wire:
    to_counters / from_counters), summed by the supervisor over capture's restarts."""

    produced: int = 0  # pairs sent to the broker
    dropped: int = 0  # the broker was not reading
    failures: dict[str, int] = {}  # pairs read but skipped, by kind (unreadable, size...)
    source_errors: int = 0  # a live source lost and reopened
    source_gave_up: int = 0  # 1 once a finite source failed for good
    next_seq: int = 0  # the seq the next pair gets
    sync: dict[str, int] = {}  # live cameras paired by timestamp: sync_<stat>

    @property
    def failed(self) -> int:
        return sum(self.failures.values())

    def to_counters(self) -> dict[str, int]:
        out = {"produced": self.produced, "dropped": self.dropped, "failed": self.failed,
               "source_errors": self.source_errors, "source_gave_up": self.source_gave_up,
               "next_seq": self.next_seq}
        out.update({f"{FAILED_PREFIX}{k}": n for k, n in self.failures.items()})
        out.update(self.sync)
        return out

    @classmethod
    def from_counters(cls, c: dict[str, int]) -> CaptureCounters:
        return cls(produced=c.get("produced", 0), dropped=c.get("dropped", 0),
                   failures={k[len(FAILED_PREFIX):]: n for k, n in c.items()
                             if k.startswith(FAILED_PREFIX)},
                   source_errors=c.get("source_errors", 0),
                   source_gave_up=c.get("source_gave_up", 0), next_seq=c.get("next_seq", 0),
                   sync={k: n for k, n in c.items() if k.startswith("sync_")})

    def __add__(self, other: CaptureCounters) -> CaptureCounters:
        """Counters of two capture processes of one run (next_seq: the later one's)."""
        fails = dict(self.failures)
        for k, n in other.failures.items():
            fails[k] = fails.get(k, 0) + n
        return CaptureCounters(
            produced=self.produced + other.produced, dropped=self.dropped + other.dropped,
            failures=fails, source_errors=self.source_errors + other.source_errors,
            source_gave_up=max(self.source_gave_up, other.source_gave_up),
            next_seq=max(self.next_seq, other.next_seq), sync=other.sync or self.sync)


class Alive(Msg, frozen=True, tag="alive"):
    """An idle worker's heartbeat to the broker, with how many jobs it could take now."""

    worker: str
    pool: str
    free: int = 0


class Gone(Msg, frozen=True, tag="gone"):
    """Supervisor (or a stopping worker) -> broker: this worker is gone; its pairs are lost."""

    worker: str
    reason: str = ""


GONE_STOPPING = "stopping"  # Gone.reason of a worker that leaves on a stop request
# Gone.reason of a worker recycled (pool max_rss_mb or max_jobs): "recycled:rss ...". It
# answered its last pair before saying so; what was sent to it after that goes to another.
GONE_RECYCLED = "recycled:"


def recycled_reason(why: str, detail: str = "") -> str:
    """The Gone.reason of a recycled worker (`why`: rss or jobs)."""
    return f"{GONE_RECYCLED}{why}{f' ({detail})' if detail else ''}"


def is_planned_goodbye(reason: str) -> bool:
    """Whether a Gone.reason tells of a worker leaving on purpose (stop, recycle): its
    departure is news for the debug log only."""
    return reason == GONE_STOPPING or reason.startswith(GONE_RECYCLED)


class ResultsAck(Msg, frozen=True, tag="ack"):
    """Normalizer -> broker: the first `count` results it was sent are written; forget them."""

    count: int


class Done(Msg, frozen=True, tag="done"):
    """A worker finished a job; frame 1 is the encoded Result. Returns one credit."""

    worker: str
    pool: str
    seq: int


class Failed(Msg, frozen=True, tag="failed"):
    """A worker could not process a pair (bad input, plugin error). Returns one credit."""

    worker: str
    pool: str
    seq: int
    reason: str
    kind: str = "error"  # short class of the failure (exception name), for the ledger


# --- remote workers (another host, over CURVE) -------------------------------------

_Short = Annotated[str, msgspec.Meta(min_length=1, max_length=128)]


class JoinRequest(Msg, frozen=True, tag="join_request"):
    """`trapflow worker` -> broker: how does this pool run? Answered by a Welcome."""

    pool: _Short
    host: _Short


class Hello(Msg, frozen=True, tag="hello"):
    """A remote worker process joins a pool; `owner` is its local supervisor's identity,
    which may tell of its death (Gone). Answered by a Welcome; Ready follows."""

    worker: _Short
    pool: _Short
    host: _Short
    owner: _Short


class HostAlive(Msg, frozen=True, tag="host_alive"):
    """A `trapflow worker` supervisor's heartbeat: its host is up. Its workers are silent
    while they compute; when their supervisor is silent too, the host is gone."""

    host: _Short


class Welcome(Msg, frozen=True, tag="welcome"):
    """Broker -> remote: the pool's plugin configuration and the run's rig, as plain data
    (the receiver validates them into its own Structs), or why it may not join."""

    pool: str
    plugin: str = ""
    pool_config: dict[str, Any] = {}
    rig: dict[str, Any] = {}
    heartbeat_interval_s: float = 1.0
    error: str = ""


# A pool's or a parameter's name on the control path: short, plain, safe to log.
ControlName = Annotated[str, msgspec.Meta(min_length=1, max_length=64,
                                          pattern=r"^[A-Za-z_][A-Za-z0-9_.\-]*$")]
PolicyText = Annotated[str, msgspec.Meta(min_length=1, max_length=64)]


ParamValue = Union[Annotated[str, msgspec.Meta(max_length=256)], int, float, bool, None]
# A pool's whole params mapping (config values may be lists or maps), bounded in keys here
# and in bytes by the header limit.
Params = Annotated[dict[ControlName, Any], msgspec.Meta(max_length=64)]


class PoolSwitch(Msg, frozen=True, tag="pool_switch"):
    """Supervisor -> broker: a pool becomes (in)active, takes a new policy, or new plugin
    parameters that its workers apply in place (None: as is). An inactive pool counts every
    pair it would have queued as dropped-while-inactive."""

    pool: ControlName
    active: bool | None = None
    policy: PolicyText | None = None
    params: Params | None = None
    # At most one pair per this many seconds (the degradation ladder; 0: no limit).
    min_interval_s: Annotated[float, msgspec.Meta(ge=0, le=3600)] | None = None


class LadderLevel(Msg, frozen=True, tag="ladder_level"):
    """Supervisor -> broker: the degradation ladder's level and why, published in Stats
    so that every view (status, viewer, the modem's health records) reads it."""

    level: ControlName
    reason: Annotated[str, msgspec.Meta(max_length=256)] = ""


class Stopping(Msg, frozen=True, tag="stopping"):
    """Supervisor -> broker: a planned stop begins (duration, stop request, signal, drained
    source); workers leave from now on, so a send to one that already left is no news."""


class Configure(Msg, frozen=True, tag="configure"):
    """Broker -> each worker of a pool (one frame): configure the plugin again with these
    parameters, between pairs."""

    pool: ControlName
    params: Params


# One spelling per union: msgspec decodes it, and annotations name it.
WorkerMsg = (Ready | Alive | Done | Failed | Gone | Hello | JoinRequest | HostAlive | PoolSwitch
             | LadderLevel | Stopping)


# --- stats and control ----------------------------------------------------------


class PoolStats(Msg, frozen=True):
    """Counters of one pool, as the broker sees them; wire.pool_counters lists them."""

    workers: int = 0
    received: int = 0
    dispatched: int = 0
    dropped: int = 0
    in_flight: int = 0
    pending: int = 0
    processed: int = 0
    errors: int = 0  # failed pairs (bad input, plugin error); by kind in `failures`
    timed_out: int = 0  # a worker held the pair longer than the pool's timeout_s
    lost: int = 0  # the worker holding it died, or the run stopped before it finished
    inactive: int = 0  # dropped because the pool was deactivated (trapflow pool --deactivate)
    throttled: int = 0  # dropped by the ladder's level: inside the pool's minimum interval
    stale: int = 0  # dropped after waiting longer than the pool's max_pending_age_s
    gated: int = 0  # withheld by the motion gate (gate: motion): never given, by design
    cut: int = 0  # detections cut from results beyond the pool's max_detections (boxes)
    kept: int = 0  # withheld for now as the gate's pre-roll: fed on motion, else gated
    failures: dict[str, int] = {}
    rate: float = 0.0  # processed per second over the last interval
    active: bool = True
    min_interval_s: float = 0.0  # the ladder's minimum interval between pairs (0: none)
    latency_ms: float = 0.0  # arrival at the broker to answer, moving average


class RemoteWorker(Msg, frozen=True):
    """One worker process on another host, as the broker sees it."""

    worker: str
    host: str
    pool: str
    state: str  # active, evicted
    processed: int = 0
    rate: float = 0.0  # processed per second over the last interval
    reason: str = ""  # why it was evicted


# The first frame of capture's out-of-band image-health message to the broker
# ([IMAGE_HEALTH, ImageHealth]); the broker keeps the latest and publishes it in its Stats.
IMAGE_HEALTH = b"image_health"


ImageState = Literal["learning", "ok", "fouled", "turbid", "fouled+turbid"]


class ImageHealth(Msg, frozen=True, tag="image_health"):
    """What capture's image-health watch says now (trapflow.image_health): the state and
    each statistic's ratio to the deployment's baseline (1.0: as at the start; 0.0 while
    the baseline is learnt)."""

    state: ImageState = "learning"
    sharpness: float = 0.0  # fine detail for the image's own contrast, to its baseline
    contrast: float = 0.0  # spread of grey levels for the brightness, to its baseline
    brightness: float = 0.0  # mean grey level, to its baseline
    samples: int = 0  # pairs looked at so far
    changes: int = 0  # times the state changed after the baseline was learnt


class Stats(Msg, frozen=True, tag="stats"):
    """Published once a second on the tap: the numbers every view reads."""

    t_wall_ns: int
    uptime_s: float
    pairs_in: int
    rate_in: float
    malformed: int
    pools: dict[str, PoolStats]
    remote: list[RemoteWorker] = []
    level: str = ""  # the degradation ladder's level ("": no ladder)
    level_reason: str = ""
    image: ImageHealth | None = None  # capture's image-health watch, the latest it told


# --- codecs ---------------------------------------------------------------------


def _enc_hook(obj: Any) -> Any:
    # numpy scalars (np.float32 from OpenCV, np.int64 from indexing) become Python numbers.
    item = getattr(obj, "item", None)
    if item is not None and getattr(obj, "shape", None) == ():
        return item()
    raise NotImplementedError(f"cannot encode {type(obj).__name__}")


_enc = msgspec.msgpack.Encoder(enc_hook=_enc_hook)
_pair_dec = msgspec.msgpack.Decoder(StereoPair)
_job_dec = msgspec.msgpack.Decoder(Job)
_worker_dec = msgspec.msgpack.Decoder(WorkerMsg)
_result_dec = msgspec.msgpack.Decoder(Result)
_ack_dec = msgspec.msgpack.Decoder(ResultsAck)
_stats_dec = msgspec.msgpack.Decoder(Stats)
_heartbeat_dec = msgspec.msgpack.Decoder(Heartbeat)
_configure_dec = msgspec.msgpack.Decoder(Configure)


def encode(msg: Msg) -> bytes:
    """Encode any message struct to msgpack bytes."""
    return _enc.encode(msg)


def decode_bounded(dec: msgspec.msgpack.Decoder[Any] | msgspec.json.Decoder[Any], data: Buffer,
            what: str, limit: int) -> Any:
    buf = memoryview(data.buffer if hasattr(data, "buffer") else data)
    if buf.nbytes > limit:
        raise ProtocolError(f"{what}: expected at most {limit} bytes, got {buf.nbytes}")
    try:
        return dec.decode(buf)
    except msgspec.DecodeError as exc:
        raise ProtocolError(f"{what}: {exc}") from None


def decode_pair_header(data: Buffer) -> StereoPair:
    """Decode and sanity-check a StereoPair header frame."""
    pair: StereoPair = decode_bounded(_pair_dec, data, "pair header", MAX_HEADER_BYTES)
    if not (0 < pair.width <= MAX_SIDE and 0 < pair.height <= MAX_SIDE):
        raise ProtocolError(
            f"pair header: expected width and height in 1..{MAX_SIDE}, "
            f"got {pair.width}x{pair.height}"
        )
    if pair.seq < 0:
        raise ProtocolError(f"pair header: expected seq >= 0, got {pair.seq}")
    return pair


def raw_size(pair: StereoPair) -> int:
    """Bytes of one raw BGR image of this pair."""
    return pair.width * pair.height * 3


def check_pair_frames(frames: Sequence[Buffer]) -> StereoPair:
    """Validate a [header, left, right] message and return its header."""
    if len(frames) != 3:
        raise ProtocolError(f"pair: expected 3 frames [header, left, right] or 2 "
                            f"[header, frame ref], got {len(frames)}")
    pair = decode_pair_header(frames[0])
    limit = raw_size(pair)
    for side, frame in (("left", frames[1]), ("right", frames[2])):
        n = len(frame)
        if pair.encoding == "raw" and n != limit:
            raise ProtocolError(
                f"pair {pair.seq}: {side} raw image expected {limit} bytes, got {n}")
        if pair.encoding == "jpeg" and not 0 < n <= limit:
            raise ProtocolError(
                f"pair {pair.seq}: {side} JPEG expected 1..{limit} bytes, got {n}"
            )
    return pair


def decode_job(data: Buffer) -> Job:
    """Decode the job frame a worker receives before a pair."""
    job: Job = decode_bounded(_job_dec, data, "job", MAX_HEADER_BYTES)
    return job


def decode_configure(data: Buffer) -> Configure:
    """Decode the broker's one-frame Configure message to a worker."""
    msg: Configure = decode_bounded(_configure_dec, data, "configure", MAX_HEADER_BYTES)
    return msg


def decode_worker_msg(data: Buffer) -> WorkerMsg:
    """Decode frame 0 of a message a worker (or the supervisor) sent to the broker."""
    msg: WorkerMsg = decode_bounded(_worker_dec, data, "worker message", MAX_HEADER_BYTES)
    return msg


_welcome_dec = msgspec.msgpack.Decoder(Welcome)


def decode_welcome(data: Buffer) -> Welcome:
    """Decode the broker's answer to a JoinRequest or Hello."""
    welcome: Welcome = decode_bounded(_welcome_dec, data, "welcome", MAX_RESULT_BYTES)
    return welcome


def decode_results_ack(data: Buffer) -> ResultsAck:
    """Decode the normalizer's acknowledgement of written results."""
    ack: ResultsAck = decode_bounded(_ack_dec, data, "results ack", MAX_HEADER_BYTES)
    if ack.count < 0:
        raise ProtocolError(f"results ack: expected a count >= 0, got {ack.count}")
    return ack


def decode_result(data: Buffer) -> Result:
    """Decode an encoded Result."""
    res: Result = decode_bounded(_result_dec, data, "result", MAX_RESULT_BYTES)
    return res


def decode_stats(data: Buffer) -> Stats:
    """Decode a Stats message from the tap."""
    stats: Stats = decode_bounded(_stats_dec, data, "stats", MAX_RESULT_BYTES)
    return stats


def decode_heartbeat(data: Buffer) -> Heartbeat:
    """Decode a Heartbeat a node sent to the supervisor."""
    hb: Heartbeat = decode_bounded(_heartbeat_dec, data, "heartbeat", MAX_HEADER_BYTES)
    return hb


_image_health_dec = msgspec.msgpack.Decoder(ImageHealth)


def decode_image_health(data: Buffer) -> ImageHealth:
    """Decode capture's ImageHealth message."""
    msg: ImageHealth = decode_bounded(_image_health_dec, data, "image health", MAX_HEADER_BYTES)
    return msg


_truth_dec = msgspec.msgpack.Decoder(Truth)


def decode_truth(data: Buffer) -> Truth:
    """Decode a Truth message from the tap."""
    truth: Truth = decode_bounded(_truth_dec, data, "truth", MAX_RESULT_BYTES)
    return truth


_line_dec = msgspec.json.Decoder(dict[str, dict[str, Any]])


def decode_result_line(data: Buffer) -> tuple[str, dict[str, Any]]:
    """Decode one JSON line of the normalizer's result tap: (algorithm, its fields)."""
    obj: dict[str, dict[str, Any]] = decode_bounded(_line_dec, data, "result line",
                                                    MAX_RESULT_BYTES)
    if len(obj) != 1:
        raise ProtocolError(f"result line: expected one key (the algorithm), got {len(obj)}: "
                            f"{sorted(obj)[:5]}")
    ((kind, fields),) = obj.items()
    return kind, fields


# A log record with a traceback can be long; past this a node cuts the message.
MAX_LOG_BYTES = 64 << 10


def to_builtins(msg: Msg) -> Any:
    """Plain Python builtins (dicts, lists, numbers) for a message, for JSON output."""
    return msgspec.to_builtins(msg)
