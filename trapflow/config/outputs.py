"""What a run writes: events around triggers, the normalizer's result lines, tracking and
counting (observe:), the exports and the recording."""

from __future__ import annotations

from typing import Annotated

import msgspec

from trapflow.config.base import Section as _Section


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
    max_boxes: Annotated[int, msgspec.Meta(ge=1, le=100000)] = 300
    """Most boxes of one pair that tracking takes, the most confident; the rest get track
    null and are counted (normalizer counter capped_for_tracking)."""

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
