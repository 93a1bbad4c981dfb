"""Configuration of the modem link (port, rates, budget, priorities, TTL and aggregation),
its outbox and its health records: config structs only, imported by trapflow.config.schema, so this
module imports nothing of the runtime (the frame and codec modules take their limits from
here)."""

from __future__ import annotations

import fnmatch
from typing import Annotated

import msgspec

BITS_PER_BYTE = 10  # 8N1 on the serial side: start, 8 data bits, stop
MAX_PAYLOAD = 255  # largest payload a link frame can carry (its length is one byte)
# The link encoding's label table (an index per label); the surface must use the same one.
DEFAULT_LABELS = (
    "crab", "scallop", "fish", "starfish", "lobster", "urchin", "octopus", "shrimp",
    "jellyfish", "ray", "background",
)  # fmt: skip


def _priorities() -> list[str]:
    # Observations first: a label seen for the first time in the run and a new MaxN are
    # the news, then interval counts (MaxN, visits) and finished tracks answer the
    # questions asked of a trap in a few bytes; the thumbnails of tracks queued for review
    # (a few hundred bytes each) come next, then per-pair detections.
    return ["new_label", "new_max_n", "counts", "track", "thumb", "stereo_ir/scallop",
            "mono_ir/crab",
            "health", "tags", "stereo_ir/*", "mono_ir/*", "stereo_vo", "*"]  # fmt: skip


class ModemConfig(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """The modem sink: results from the outbox to the surface over a serial link."""

    enabled: bool = False
    """Run the modem sender."""
    port: str = ""
    """Serial device path or pyserial URL (loop://, a pty path...)."""
    baudrate: Annotated[int, msgspec.Meta(ge=50, le=4_000_000)] = 9600
    """Speed of the serial port between the computer and the modem."""
    bit_rate: Annotated[float, msgspec.Meta(gt=0, le=1_000_000)] = 300.0
    """Bit rate of the acoustic link; the sender never sends faster (10 bits per byte)."""
    bytes_per_hour: Annotated[int, msgspec.Meta(ge=0)] = 0
    """Budget of bytes sent in any hour (frames and retransmissions); 0 means no budget. Data
    and repeated replies stop at 90 % of it: the rest is kept for replies to new commands."""
    max_frame_payload: Annotated[int, msgspec.Meta(ge=32, le=MAX_PAYLOAD)] = 96
    """Largest DATA payload; smaller frames lose less to a damaged bit."""
    window: Annotated[int, msgspec.Meta(ge=1, le=64)] = 4
    """Frames in flight (unacknowledged) at once."""
    ack_timeout_s: Annotated[float, msgspec.Meta(gt=0, le=600)] = 3.0
    """Wait for an acknowledgement this long beyond the frames' airtime before resending."""
    backoff: Annotated[float, msgspec.Meta(ge=1, le=10)] = 2.0
    """Each resend of the same message waits this factor longer."""
    backoff_max_s: Annotated[float, msgspec.Meta(gt=0, le=3600)] = 60.0
    """Longest wait for an acknowledgement."""
    detections: bool = True
    """Send per-pair detection lines (mono_ir) too; false: only tracks and interval counts
    of the detector pools go out, the lines stay on disk."""
    priorities: list[str] = msgspec.field(default_factory=_priorities)
    """Message class patterns (fnmatch), most urgent first; unmatched classes come last."""
    news: list[str] = msgspec.field(default_factory=lambda: ["new_label", "new_max_n"])
    """Class patterns of the run's news (a label's first track, a new MaxN): while a record
    of one waits for its acknowledgement no other DATA frame goes out, so over a lossy link
    it reaches the surface before anything queued with it. News are rare: little cost."""
    ttl_s: dict[str, Annotated[float, msgspec.Meta(ge=0)]] = msgspec.field(
        default_factory=lambda: {"stereo_vo": 600.0, "health": 3600.0}
    )
    """Class pattern -> seconds a record may wait before it expires; the first match counts."""
    aggregate: list[str] = msgspec.field(default_factory=lambda: ["mono_ir/*", "stereo_vo"])
    """Class patterns summarised per interval (count and best) when the link is behind."""
    aggregate_interval_s: Annotated[float, msgspec.Meta(gt=0, le=86400)] = 60.0
    """Length of one aggregation interval."""
    aggregate_backlog: Annotated[int, msgspec.Meta(ge=1)] = 8
    """A class is behind when more than this many of its records wait."""
    aggregate_best: Annotated[int, msgspec.Meta(ge=0, le=16)] = 3
    """Best (highest confidence) records kept in one aggregate."""
    labels: list[str] = msgspec.field(default_factory=lambda: list(DEFAULT_LABELS))
    """Label table of the link encoding; the surface must use the same one."""
    reopen_interval_s: Annotated[float, msgspec.Meta(gt=0, le=600)] = 2.0
    """How often to retry a port that cannot be opened."""
    housekeeping_s: Annotated[float, msgspec.Meta(gt=0, le=60)] = 0.5
    """How often to look for new records, expire and aggregate."""
    command_key: str = ""
    """File holding the key shared with the surface for signed commands (mode 600, at least
    16 bytes: `head -c 32 /dev/urandom > FILE`); never the key itself. Empty: every command
    from the surface is refused."""
    command_timeout_s: Annotated[float, msgspec.Meta(gt=0, le=60)] = 5.0
    """How long a surface command waits for the supervisor; then its reply says so."""

    @property
    def bytes_per_s(self) -> float:
        """Link bytes per second."""
        return self.bit_rate / BITS_PER_BYTE

    def priority_of(self, cls: str) -> int:
        """Rank of a class: 0 is the most urgent."""
        for i, pattern in enumerate(self.priorities):
            if fnmatch.fnmatchcase(cls, pattern):
                return i
        return len(self.priorities)

    def is_news(self, cls: str) -> bool:
        """Whether a class is news (`news`): sent, then acknowledged, before anything else."""
        return any(fnmatch.fnmatchcase(cls, pattern) for pattern in self.news)

    def ttl_of(self, cls: str) -> float:
        """Seconds a record of this class may wait; 0 means forever."""
        for pattern, ttl in self.ttl_s.items():
            if fnmatch.fnmatchcase(cls, pattern):
                return ttl
        return 0.0

    def aggregates(self, cls: str) -> bool:
        """Whether this class is summarised when behind."""
        return any(fnmatch.fnmatchcase(cls, p) for p in self.aggregate)


class HealthConfig(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """The periodic health message."""

    enabled: bool = True
    """Send health records."""
    interval_s: Annotated[float, msgspec.Meta(ge=1, le=86400)] = 600.0
    """Seconds between two health records."""


class OutboxConfig(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """The durable outbox between the normalizer and the modem sender."""

    path: str = "outbox.sqlite"
    """SQLite file, relative to the run directory."""
    fsync_interval_s: Annotated[float, msgspec.Meta(gt=0, le=3600)] = 1.0
    """At most this long between an append and its fsync (what survives a power cut)."""
    retention_s: Annotated[float, msgspec.Meta(ge=0)] = 7 * 86400.0
    """Resolved (acknowledged, expired, aggregated) records are deleted this long after."""
    quota_bytes: Annotated[int, msgspec.Meta(ge=1 << 16)] = 256 << 20
    """The outbox never grows past this; resolved records go first, then appends are refused."""
    min_free_bytes: Annotated[int, msgspec.Meta(ge=0)] = 64 << 20
    """Appends are refused when the disk has less free space than this, or than 5 % of its
    partition where that is less (a small partition still takes records)."""
    max_record_bytes: Annotated[int, msgspec.Meta(ge=64, le=1 << 20)] = 16384
    """A record whose JSON is larger is refused."""
    class_fields: dict[str, str] = msgspec.field(
        default_factory=lambda: {"mono_ir": "label", "stereo_ir": "label"}
    )
    """Message class = the record's key, plus '/' and this field's value for these keys."""
