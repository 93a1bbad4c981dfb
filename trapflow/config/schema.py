"""Typed configuration: YAML decoded into Structs, unknown keys rejected, bounds checked.

Errors name the YAML path (`$.pools.vo.policy`) and what was expected. The
defaults here are the defaults; configs/default.yaml documents every key and a
test keeps the two equal. A leaf: it imports only config-struct modules (modem/config.py,
config.ladder), never a module of the runtime; those import their sections from here.
"""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec
import yaml

from trapflow.config.ladder import LadderConfig
from trapflow.config.modem import HealthConfig, ModemConfig, OutboxConfig
from trapflow.errors import ConfigError, yaml_problem


class _Section(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    pass


Positive = Annotated[float, msgspec.Meta(gt=0)]


# --- queueing policies: the grammar (the broker's policy module applies them) -------------

DEFAULT_ORDERED_BOUND = 16


@dataclass(frozen=True)
class Policy:
    """A parsed policy string."""

    kind: str  # "latest" | "fifo" | "ordered"
    bound: int

    def __str__(self) -> str:
        return "latest" if self.kind == "latest" else f"{self.kind}:{self.bound}"


def parse_policy(text: str) -> Policy:
    """Parse `latest`, `fifo:N` or `ordered[:N]`; ValueError says what was expected."""
    expected = f"expected latest, fifo:N or ordered[:N] with N >= 1, got {text!r}"
    kind, sep, num = text.strip().partition(":")
    if kind == "latest" and not sep:
        return Policy("latest", 1)
    if kind == "ordered" and not sep:
        return Policy("ordered", DEFAULT_ORDERED_BOUND)
    if kind in ("fifo", "ordered") and sep:
        try:
            bound = int(num)
        except ValueError:
            raise ValueError(expected) from None
        if bound >= 1:
            return Policy(kind, bound)
    raise ValueError(expected)


# --- sections ------------------------------------------------------------------------------


class TriggerRule(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """A result that starts or extends an event."""

    algorithm: str
    """Top-level key of the normalized result, e.g. mono_ir."""
    label: str | None = None
    """Fire only on this label (None: any label)."""
    not_label: str | None = None
    """Never fire on this label (e.g. 'none' for stereo_ir)."""
    min_confidence: Annotated[float, msgspec.Meta(ge=0, le=1)] = 0.0
    """Lowest confidence that fires."""


class EventsConfig(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """Photo-trap event capture."""

    enabled: bool = False
    """Run event capture at all."""
    triggers: list[TriggerRule] = []
    """Rules; any one firing starts or extends an event."""
    pre_s: Annotated[float, msgspec.Meta(ge=0, le=600)] = 2.0
    """Seconds of pairs kept from before the trigger."""
    post_s: Annotated[float, msgspec.Meta(ge=0, le=3600)] = 3.0
    """Seconds of pairs kept after the last trigger."""
    max_ring_pairs: Annotated[int, msgspec.Meta(ge=1, le=100_000)] = 300
    """Bound on the pre-roll ring in pairs (memory cap)."""
    quota_bytes: Annotated[int, msgspec.Meta(gt=0)] = 2 << 30
    """Most bytes all events may take; oldest deleted first."""
    min_free_bytes: Annotated[int, msgspec.Meta(ge=0)] = 512 << 20
    """Free disk space kept; oldest events deleted to keep it."""
    folder: str = "events"
    """Where event folders are written (relative to the run directory)."""



# The one JPEG quality of pairs on the wire and in recordings (source.jpeg_quality).
DEFAULT_JPEG_QUALITY = 90


class SourceConfig(_Section):
    """Where pairs come from and how they are encoded."""

    kind: str = "synthetic"
    """Where pairs come from: synthetic, video, images, v4l2, picamera2, gst or replay (`--source
    KIND:ARGS`; docs/cli.md#sources)."""
    uri: str = ""
    """The kind's location: files, a folder, devices, GStreamer pipelines or a recording (the ARGS
    of `--source KIND:ARGS`); empty for synthetic."""
    rate_hz: Annotated[float, msgspec.Meta(gt=0, le=240)] = 15.0
    """Pairs per second capture produces (a recording at its recorded pace unless replayed with
    `--rate`)."""
    width: Annotated[int, msgspec.Meta(ge=16, le=8192)] = 1280
    """Image width in pixels (of the synthetic world, or asked of a camera)."""
    height: Annotated[int, msgspec.Meta(ge=16, le=8192)] = 720
    """Image height in pixels (of the synthetic world, or asked of a camera)."""
    encoding: Literal["jpeg", "raw"] = "raw"
    """raw: the ring holds the decoded frames and every local pool reads them as they are; jpeg:
    capture encodes each side (~3 ms at 1280x720) and every pool decodes it again."""
    jpeg_quality: Annotated[int, msgspec.Meta(ge=1, le=100)] = DEFAULT_JPEG_QUALITY
    """JPEG quality of pairs on the wire and in recordings (1..100)."""
    seed: int = 1
    """Random seed of the synthetic world (1: crabs walk in after 3 s)."""
    moving: bool = False
    """The synthetic rig moves along a known trajectory."""
    loop: bool = False
    """Start a finite source again when it is exhausted (else the run ends once every pool has
    drained)."""
    options: dict[str, Any] = {}
    """Options of the source kind (e.g. the synthetic world's `tag_size_m`, a replay's `rate`)."""

    @property
    def waits_for_pools(self) -> bool:
        """A finite source read as fast as it goes (a replay at rate 0, not looped) has no
        clock to keep: capture waits for the broker's room in every pool, so the run goes at
        its slowest pool's speed and no pool drops a pair (issue 22, item 2)."""
        if self.loop or self.kind != "replay":
            return False
        try:
            return float(self.options.get("rate", 1.0)) == 0.0
        except (TypeError, ValueError):
            return False  # the source refuses it with its own message


class RigConfig(_Section):
    """The stereo rig: baseline and field of view (or a calibration file)."""

    baseline_m: Annotated[float, msgspec.Meta(gt=0, le=10)] = 0.12
    """Distance between the two cameras in metres, where the source knows none."""
    hfov_deg: Annotated[float, msgspec.Meta(gt=1, lt=179)] = 70.0
    """Horizontal field of view in degrees, where no calibration gives one."""
    calibration: str | None = None
    """Path of a stereo calibration file (docs/calibration.md); it overrides everything else."""


class PoolConfig(_Section):
    """One pool of identical worker processes running one algorithm."""

    count: Annotated[int, msgspec.Meta(ge=0, le=64)] = 1
    """Worker processes on this host (0 switches the pool off, or with `remote: true` leaves it to
    other hosts)."""
    plugin: str = ""
    """Registry name or `module:Class` of the plugin; empty: the pool's own name."""
    policy: str = "latest"
    """Queueing policy: `latest` (only the newest pair waits), `fifo:N` or `ordered[:N]` (one
    worker, in order; a drop reaches it as a gap)."""
    nice: Annotated[int, msgspec.Meta(ge=0, le=19)] = 0
    """Niceness added to the pool's processes (0..19), so visual odometry keeps its rate."""
    affinity: list[Annotated[int, msgspec.Meta(ge=0)]] = []
    """CPU cores the pool's processes may run on; empty: all."""
    credit: Annotated[int, msgspec.Meta(ge=1, le=64)] = 1
    """Pairs a worker may hold at once (prefetch)."""
    timeout_s: Annotated[float, msgspec.Meta(gt=0, le=3600)] = 10.0
    """A pair taking a worker longer than this is lost, the worker evicted and its process
    killed."""
    max_rss_mb: Annotated[int, msgspec.Meta(ge=0, le=1 << 20)] = 0
    """A worker whose resident memory (MiB) is past this after a pair is recycled: it
    finishes the pair, says goodbye and is replaced at once (0: no limit)."""
    max_jobs: Annotated[int, msgspec.Meta(ge=0)] = 0
    """A worker is recycled after this many pairs (processed or failed; 0: no limit)."""
    max_pending_age_s: Annotated[float, msgspec.Meta(ge=0, le=86400)] = 0.0
    """Pairs waiting in the pool's queue longer than this are dropped as stale (0: kept)."""
    params: dict[str, Any] = {}
    """Passed to the plugin's `configure()` (docs/plugins.md lists the built-in plugins' params)."""
    remote: bool = False
    """Workers on other hosts may join (`trapflow worker`); the broker sends them the bytes."""
    gate: Literal["always", "motion"] = "always"
    """always: every pair; motion: only pairs the motion gate lets through (the `gate:`
    section: motion, pre-roll, keep-alive, hold); the rest are counted `gated`."""
    debug: bool = False
    """The pool's processes log at debug level."""
    save: bool = False
    """The plugin may save debug images into the run directory (debug/)."""
    time: bool = False
    """Log each pair's processing time."""

    def __post_init__(self) -> None:
        policy = parse_policy(self.policy)  # raises ValueError, reported with the key path
        if self.gate == "motion" and policy.kind == "ordered":
            raise ValueError(
                f"expected gate: always with policy {self.policy}, got gate: motion: an "
                "ordered pool (visual odometry) needs every pair in sequence, and each "
                "pair the gate withholds would reach it as a gap that resets it")

    @property
    def parsed_policy(self) -> Policy:
        """The policy as an object."""
        return parse_policy(self.policy)


class NormalizerConfig(_Section):
    """The sink that writes one JSON object per result."""

    results_file: str = "results.jsonl"
    """The results file, in the run directory."""
    flush_interval_s: Annotated[float, msgspec.Meta(gt=0, le=1)] = 0.5
    """Results reach the file at least this often."""
    fsync_interval_s: Annotated[float, msgspec.Meta(gt=0, le=3600)] = 5.0
    """Results reach the disk (fsync) at least this often."""
    decimals: Annotated[int, msgspec.Meta(ge=0, le=9)] = 3
    """Digits kept in the float fields of plugin-defined results (built-in fields keep theirs)."""


class ObserveConfig(_Section):
    """Detections become observations: tracks, visits and interval counts (MaxN)."""

    enabled: bool = True
    """Track the detector pools' boxes and write tracks and interval counts."""
    tracks_file: str = "tracks.jsonl"
    """Finished tracks, one JSON object each, in the run directory."""
    counts_file: str = "counts.jsonl"
    """Closed intervals: per label visits, MaxN and dwell."""
    interval_s: Annotated[float, msgspec.Meta(gt=0, le=86400)] = 600.0
    """Length of a counting interval (aligned to multiples of it in UTC)."""
    high: Annotated[float, msgspec.Meta(ge=0, le=1)] = 0.5
    """Detections at or above this confidence are matched first and may start tracks."""
    low: Annotated[float, msgspec.Meta(ge=0, le=1)] = 0.1
    """Between low and high a detection may only extend a confirmed track."""
    iou_gate: Annotated[float, msgspec.Meta(gt=0, lt=1)] = 0.1
    """Least overlap of a track's predicted box and a detection for them to match."""
    dist_gate: Annotated[float, msgspec.Meta(ge=0, le=1000)] = 13.0
    """Else a box this close to a track's predicted box (squared Mahalanobis distance,
    widening with the time unseen) matches it; 0: off."""
    dup_iou: Annotated[float, msgspec.Meta(gt=0, le=1)] = 0.6
    """A box overlapping a more confident one of its pair this much is left out; 1: off."""
    min_hits: Annotated[int, msgspec.Meta(ge=1, le=100)] = 2
    """Detections that confirm a track and give it its id."""
    max_gap_s: Annotated[float, msgspec.Meta(gt=0, le=3600)] = 3.0
    """A track not seen for this long (capture time) has ended."""

    def __post_init__(self) -> None:
        if self.low > self.high:
            raise ValueError(f"observe: expected low <= high, got low={self.low} "
                             f"high={self.high}")


class ExportConfig(_Section):
    """Exports of a finished run (`trapflow export`)."""

    min_confidence: Annotated[float, msgspec.Meta(ge=0, le=1)] = 0.5
    """Camtrap DP: least confidence of an observation (a track's best box, or a box of a run
    without tracks); a pair with no box at or above it is a blank (`--min-confidence`)."""


class RecordingConfig(_Section):
    """Recordings (`trapflow record`)."""

    vision_msgs: str = ""
    """Folder of ROS 2 vision_msgs definitions (its msg/ folder, the package or a ROS
    prefix) for detections as vision_msgs/Detection2DArray; empty: AMENT_PREFIX_PATH's."""


class EnergyConfig(_Section):
    """The power model ledger.json's energy estimate uses (trapflow.power.energy.BOARDS)."""

    board: Literal["pi5", "orin_nano"] = "pi5"
    """Board whose power model turns CPU time into watts."""
    cameras: Annotated[int, msgspec.Meta(ge=0, le=8)] = 2
    """Cameras streaming."""
    battery_wh: Annotated[float, msgspec.Meta(ge=0)] = 0.0
    """Battery capacity; with it, the estimate says how many days it lasts (0: not said)."""
    usable: Annotated[float, msgspec.Meta(gt=0, le=1)] = 0.8
    """Share of the battery that may be drawn."""


class MotionGateConfig(_Section):
    """The motion gate's rules for every pool with `gate: motion` (docs/gate-and-energy.md)."""

    pre_roll: Annotated[int, msgspec.Meta(ge=0, le=100)] = 5
    """Withheld pairs kept in the frame ring and fed in order when motion begins; a
    `latest` pool takes none (it would keep only the newest of them), a fifo:N pool at most
    N - 1 (they are queued at once, with the pair that moved)."""
    keepalive_s: Annotated[float, msgspec.Meta(gt=0, le=86400)] = 5.0
    """One pair at least this often without motion: a still animal in view is still seen."""
    hold_s: Annotated[float, msgspec.Meta(ge=0, le=3600)] = 3.0
    """Pairs keep going for this long after the last motion (an animal pausing mid-walk)."""
    min_score: Annotated[float, msgspec.Meta(ge=0, lt=1)] = 0.0
    """Motion counts only with at least this score (share of the small image moving)."""
    busy_rate_hz: Annotated[float, msgspec.Meta(ge=0, le=240)] = 3.0
    """While the gate is open (motion, hold, a live track), at most this many pairs per
    second of capture time to each gated pool (0: every pair); the first pair of a motion
    onset and its pre-roll always go, the rest are counted `gated`. Tracks and counts keep
    (the tracker bridges the gaps); a length gets fewer views (docs/gate-and-energy.md)."""
    rig_moving_m_s: Annotated[float, msgspec.Meta(gt=0, le=100)] = 0.05
    """Visual odometry's speed from which the rig moves: the gate is off (every pair fed)
    until it is still again (docs/gate-and-energy.md)."""
    rig_moving_deg_s: Annotated[float, msgspec.Meta(gt=0, le=3600)] = 3.0
    """VO's rotation rate from which the rig moves."""
    rig_still_s: Annotated[float, msgspec.Meta(ge=0, le=3600)] = 2.0
    """Seconds below half of both before the rig is still and the gate on again."""
    idle_after_s: Annotated[float, msgspec.Meta(ge=0, le=86400)] = 0.0
    """Duty cycling, opt-in: seconds without motion before capture drops to idle_rate_hz
    (0: never). The first pair that moves brings the full rate back."""
    idle_rate_hz: Annotated[float, msgspec.Meta(gt=0, le=240)] = 2.0
    """Capture rate while idle (at most source.rate_hz): below VO's 10 pairs/s, a choice."""


class SupervisorConfig(_Section):
    """Heartbeats, restarts and the stop ladder."""

    heartbeat_interval_s: Annotated[float, msgspec.Meta(gt=0, le=60)] = 1.0
    """Every node sends a heartbeat this often."""
    liveness_s: Annotated[float, msgspec.Meta(gt=0, le=600)] = 5.0
    """A node (or a remote worker host) silent this long is taken for dead: restarted, or its
    workers evicted (a worker busy with a pair: its pool's timeout_s)."""
    restart_backoff_s: Annotated[float, msgspec.Meta(ge=0, le=60)] = 0.5
    """First restart delay, doubled at each restart."""
    restart_backoff_max_s: Annotated[float, msgspec.Meta(ge=0, le=600)] = 10.0
    """Longest restart delay."""
    max_restarts: Annotated[int, msgspec.Meta(ge=0)] = 5
    """Restarts of a node allowed within restart_window_s before it is given up."""
    restart_window_s: Annotated[float, msgspec.Meta(gt=0)] = 60.0
    """The window in which max_restarts are counted."""
    retry_cooldown_s: Annotated[float, msgspec.Meta(ge=0, le=86400)] = 60.0
    """A node given up (its restart budget spent) is retried this long after, with a fresh
    budget; essential nodes (broker, capture, normalizer) are never given up."""
    stop_timeout_s: Annotated[float, msgspec.Meta(gt=0, le=4)] = 2.0
    """Stop ladder: a node asked to stop has this long before it is killed."""
    startup_timeout_s: Annotated[float, msgspec.Meta(gt=0, le=3600)] = 60.0
    """How long every node has to report its first state before start-up is declared
    failed; more on a slow board or under emulation, where imports and the synthetic
    world's set-up take minutes."""


class LogFileConfig(_Section):
    """trapflow.log in the run directory: rotated at max_bytes, keeping `backups` old files."""

    max_bytes: Annotated[int, msgspec.Meta(ge=65536)] = 10 << 20
    """trapflow.log is rotated when it reaches this size."""
    backups: Annotated[int, msgspec.Meta(ge=1, le=100)] = 3
    """Old logs kept (trapflow.log.1 .. trapflow.log.N)."""


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


class RemoteConfig(_Section):
    """Where worker pools on other hosts connect (`trapflow worker --connect`), and the
    CURVE keys that guard it. Off while `bind` is empty."""

    bind: str = ""
    """tcp://HOST:PORT the broker binds for remote workers; beyond loopback only with keys."""
    server_key: str = ""
    """The pipeline's secret key file (NAME.key_secret from `trapflow keys generate`)."""
    authorized_keys: str = ""
    """Folder of the public keys (*.key) of the workers that may connect."""

    def __post_init__(self) -> None:
        if bool(self.server_key) != bool(self.authorized_keys):
            raise ValueError(
                "expected both server_key and authorized_keys (CURVE) or neither, got only "
                f"{'server_key' if self.server_key else 'authorized_keys'}; "
                "make keys with `trapflow keys generate DIR`")
        if not self.bind:
            return
        scheme, sep, rest = self.bind.partition("://")
        host, colon, port = rest.rpartition(":")
        if scheme != "tcp" or not sep or not colon or not host or not port.isdigit() or not (
                1024 <= int(port) <= 65535):
            raise ValueError(f"expected bind as tcp://HOST:PORT with a port in 1024..65535, "
                             f"got {self.bind!r}")
        if not _is_loopback(host.strip("[]")) and not self.server_key:
            raise ValueError(
                f"binding {self.bind!r} beyond loopback needs CURVE keys: expected "
                "server_key and authorized_keys, got none; make them with "
                "`trapflow keys generate DIR` or bind tcp://127.0.0.1:PORT")

    @property
    def curve(self) -> bool:
        """Remote workers must prove a key in authorized_keys."""
        return bool(self.server_key)


class NetworkConfig(_Section):
    """Endpoints: ipc:// files in the run directory, reachable only by its owner; remote
    workers connect to a TCP port of their own (`remote`), guarded by CURVE keys."""

    transport: Literal["ipc", "tcp"] = "ipc"
    """Kept for older configs: since issue 26 item 3 `tcp` puts nothing on TCP ports (other
    local users read frames and forged results there); every local socket is ipc."""
    host: str = "127.0.0.1"
    """Kept for older configs: a loopback address only (the pipeline's endpoints never leave the
    host)."""
    base_port: Annotated[int, msgspec.Meta(ge=1024, le=65000)] = 5550
    """Kept for older configs; no socket uses it (see transport)."""
    remote: RemoteConfig = msgspec.field(default_factory=RemoteConfig)

    def __post_init__(self) -> None:
        if not _is_loopback(self.host):
            raise ValueError(
                f"expected a loopback host (127.0.0.1), got {self.host!r}: the pipeline's own "
                "endpoints never leave this host; workers on other hosts connect to "
                "network.remote.bind, guarded by CURVE keys"
            )


class FramesConfig(_Section):
    """How images travel from capture to the workers on one host."""

    transport: Literal["zmq", "shm"] = "shm"
    """shm: written once into a shared-memory ring, only a descriptor rides on ZeroMQ;
    zmq: the bytes ride in the messages (what remote pools always get)."""
    spare_slots: Annotated[int, msgspec.Meta(ge=0, le=1024)] = 9
    """Ring slots beyond what the pools can hold: pairs between capture and the broker."""
    preroll_slots: Annotated[int, msgspec.Meta(ge=0, le=1024)] = 0
    """Ring slots kept for an event pre-roll."""


class ViewerConfig(_Section):
    """The live web viewer and its metrics (`trapflow start --view`, `trapflow view`)."""

    enabled: bool = False
    """Run the viewer as a node of the pipeline."""
    host: str = "127.0.0.1"
    """Address the web page binds to; loopback unless you mean to show it to the network."""
    port: Annotated[int, msgspec.Meta(ge=1, le=65535)] = 8090
    """TCP port of the web page and of /metrics."""
    frame_hz: Annotated[float, msgspec.Meta(gt=0, le=15)] = 2.0
    """Pairs per second shown in the page: the broker makes a small preview this often,
    and only while a page is open."""
    metrics_file: str = ""
    """node_exporter textfile written atomically every metrics_interval_s ("" = none)."""
    metrics_interval_s: Annotated[float, msgspec.Meta(ge=1, le=600)] = 5.0
    """Seconds between two writes of metrics_file."""
    allowed_hosts: list[str] = []
    """Host names the page may be reached by besides the loopback names (and, off loopback,
    the bind address, this machine's name and IP addresses): any other Host is refused, so a
    DNS-rebinding page cannot read or drive the viewer."""
    token_file: str = ""
    """File holding the token a non-loopback bind asks for (mode 600, at least 16
    characters); "" = a new token each run, printed with the URL. Loopback needs none."""


def _default_pools() -> dict[str, PoolConfig]:
    return {
        # Visual odometry keeps its rate: the recognisers run at a lower CPU priority, and
        # only on pairs the motion gate lets through (an empty sea floor costs almost
        # nothing; a rig that VO sees moving turns the gate off). VO is never gated.
        "mono": PoolConfig(count=1, policy="latest", nice=5, gate="motion"),
        "stereo": PoolConfig(count=1, policy="latest", nice=10, gate="motion"),
        "vo": PoolConfig(count=1, policy="ordered:16"),
        "tags": PoolConfig(count=0, policy="latest", nice=5),
    }


class Config(_Section):
    """The whole pipeline."""

    source: SourceConfig = msgspec.field(default_factory=SourceConfig)
    rig: RigConfig = msgspec.field(default_factory=RigConfig)
    pools: dict[str, PoolConfig] = msgspec.field(default_factory=_default_pools)
    """One pool of worker processes per algorithm, by name; a pool a config names changes only the
    keys it gives (the defaults: mono, stereo, vo, tags)."""
    normalizer: NormalizerConfig = msgspec.field(default_factory=NormalizerConfig)
    observe: ObserveConfig = msgspec.field(default_factory=ObserveConfig)
    export: ExportConfig = msgspec.field(default_factory=ExportConfig)
    recording: RecordingConfig = msgspec.field(default_factory=RecordingConfig)
    energy: EnergyConfig = msgspec.field(default_factory=EnergyConfig)
    gate: MotionGateConfig = msgspec.field(default_factory=MotionGateConfig)
    supervisor: SupervisorConfig = msgspec.field(default_factory=SupervisorConfig)
    network: NetworkConfig = msgspec.field(default_factory=NetworkConfig)
    frames: FramesConfig = msgspec.field(default_factory=FramesConfig)
    outbox: OutboxConfig = msgspec.field(default_factory=OutboxConfig)
    modem: ModemConfig = msgspec.field(default_factory=ModemConfig)
    health: HealthConfig = msgspec.field(default_factory=HealthConfig)
    events: EventsConfig = msgspec.field(default_factory=EventsConfig)
    viewer: ViewerConfig = msgspec.field(default_factory=ViewerConfig)
    ladder: LadderConfig = msgspec.field(default_factory=LadderConfig)
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    """Least level logged by every process to trapflow.log (standard error shows warnings
    and above)."""
    log_file: LogFileConfig = msgspec.field(default_factory=LogFileConfig)

    def __post_init__(self) -> None:
        for name, pool in self.pools.items():
            if not name.isidentifier():
                raise ValueError(f"pool name {name!r} must be an identifier")
            if pool.parsed_policy.kind == "ordered" and pool.count > 1:
                raise ValueError(
                    f"pool {name!r}: the ordered policy takes count 0 or 1, got {pool.count}"
                )

    def validated(self) -> Config:
        """Re-run validation after programmatic changes."""
        return from_data(msgspec.to_builtins(self), "config")

    def plugin_of(self, pool: str) -> str:
        """The plugin name a pool runs."""
        return self.pools[pool].plugin or pool


def _pool_data(name: str, pool: Any) -> Any:
    """A user's pool merged key by key over that pool's defaults (a new name: PoolConfig's)."""
    if not isinstance(pool, dict):
        return pool  # not a mapping: left for msgspec to reject with the path
    default = _default_pools().get(name)
    base = msgspec.to_builtins(default) if default is not None else {}
    return {**base, **pool}


def _check_pool(name: str, pool: Any, origin: str) -> None:
    """Validate one pool so that errors name the pool's leaf key, not `$.pools[...]`."""
    policy = pool.get("policy") if isinstance(pool, dict) else None
    if isinstance(policy, str):
        try:
            parse_policy(policy)
        except ValueError as exc:
            raise ConfigError(f"{origin}: {exc} - at `$.pools.{name}.policy`") from None
    try:
        msgspec.convert(pool, PoolConfig, strict=True)
    except msgspec.ValidationError as exc:
        msg = str(exc).replace("`$", f"`$.pools.{name}")
        if "- at `$" not in msg:
            msg += f" - at `$.pools.{name}`"
        raise ConfigError(f"{origin}: {msg}") from None


def from_data(data: Any, origin: str = "config") -> Config:
    """Validate plain data (from YAML) into a Config; ConfigError names the bad key.

    A `pools:` section changes only what it names: each pool it gives is merged key by
    key over that pool's defaults, and the default pools it does not name stay as they are.
    """
    if data is None:
        data = {}
    pools = data.get("pools") if isinstance(data, dict) else None
    if isinstance(pools, dict):
        merged = {name: msgspec.to_builtins(p) for name, p in _default_pools().items()}
        for name, pool in pools.items():
            merged[name] = _pool_data(str(name), pool)
            _check_pool(str(name), merged[name], origin)
        data = {**data, "pools": merged}
    try:
        return msgspec.convert(data, Config, strict=True)
    except msgspec.ValidationError as exc:
        raise ConfigError(f"{origin}: {exc}") from None


def load(path: str | Path | None = None) -> Config:
    """Load a YAML config file, or the built-in defaults when path is None."""
    if path is None:
        return Config()
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read config {p}: {exc.strerror}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: not valid YAML: {yaml_problem(exc)}") from None
    return from_data(data, str(p))


def parse_workers(text: str) -> dict[str, int]:
    """Parse `NAME=COUNT[,NAME=COUNT...]` into a dict; ConfigError names the bad part."""
    expected = "expected NAME=COUNT[,NAME=COUNT...]"
    counts: dict[str, int] = {}
    if not text.strip():
        raise ConfigError(f"{expected}, got an empty string")
    for part in text.split(","):
        name, sep, num = part.strip().partition("=")
        if not sep or not name.isidentifier():
            raise ConfigError(f"{expected}, got {part!r}")
        try:
            count = int(num)
        except ValueError:
            raise ConfigError(f"{expected} with an integer COUNT, got {part!r}") from None
        if count < 0:  # 0: a remote pool with no local worker (checked by with_workers)
            raise ConfigError(f"worker count must be 0 or more, got {part!r}")
        if name in counts:
            raise ConfigError(f"algorithm {name!r} given twice in {text!r}")
        counts[name] = count
    return counts


def with_workers(cfg: Config, counts: dict[str, int], known: list[str]) -> Config:
    """Run exactly the named pools with these counts; others are switched off.

    A name that is not a configured pool but is a known plugin gets a default pool. A count
    of 0 names a remote pool that runs no local worker (its workers join from other hosts).
    """
    for name, count in counts.items():
        if count == 0 and not (name in cfg.pools and cfg.pools[name].remote):
            raise ConfigError(
                f"--workers {name}=0: a pool with no local worker needs workers from other "
                f"hosts; set pools.{name}.remote: true in the config, or give {name} a count "
                "of 1 or more, or leave it out")
    pools: dict[str, PoolConfig] = {}
    for name, pool in cfg.pools.items():
        pools[name] = msgspec.structs.replace(pool, count=counts.get(name, 0))
    for name, count in counts.items():
        if name not in pools:
            if name not in known:
                choices = ", ".join(sorted(set(known) | set(cfg.pools)))
                raise ConfigError(
                    f"unknown algorithm {name!r} in --workers: expected one of {choices}")
            pools[name] = PoolConfig(count=count)
    try:
        return msgspec.structs.replace(cfg, pools=pools).validated()
    except ValueError as exc:
        raise ConfigError(str(exc)) from None



def with_source(cfg: Config, **changes: Any) -> Config:
    """Override source fields (from command-line flags), re-validated."""
    if not changes:
        return cfg
    return msgspec.structs.replace(
        cfg, source=msgspec.structs.replace(cfg.source, **changes)
    ).validated()


def with_section(cfg: Config, section: str, **changes: Any) -> Config:
    """Override fields of one section (from command-line flags), re-validated."""
    if not changes:
        return cfg
    return msgspec.structs.replace(
        cfg, **{section: msgspec.structs.replace(getattr(cfg, section), **changes)}
    ).validated()
