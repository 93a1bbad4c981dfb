"""Camtrap DP observation rows, pure: a run's tracks and detector boxes in, rows out.

An event-level row per track (the track is the event and the individual), the media-level
row of each track's best frame, linked to it by `eventID`, and a blank row per image with no
box at or above the confidence cut. A run without tracks.jsonl (tracking off, or a run from
before it) gets one media-level row per box, as before tracking existed. camtrapdp.py reads
the run and writes the package; docs/exports.md has the field map.
"""

from __future__ import annotations

import datetime as dt
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

# Camtrap DP's allowed range of individualPositionAngle (degrees from the camera's axis).
MAX_ANGLE_DEG = 90.0
# Two times closer than this are the same capture (results and tracks keep milliseconds).
SAME_TIME_S = 0.0015


def iso(t: dt.datetime) -> str:
    """Camtrap DP's datetime: ISO 8601 in UTC, to the second."""
    return t.strftime("%Y-%m-%dT%H:%M:%SZ")


def utc(t_s: float) -> dt.datetime:
    """UTC seconds (tracks.jsonl) as an aware datetime."""
    return dt.datetime.fromtimestamp(t_s, dt.timezone.utc)


@dataclass(frozen=True)
class Detection:
    """One box of a mono_ir line."""

    seq: int
    time: dt.datetime
    label: str
    confidence: float
    box: tuple[float, float, float, float]
    model: str
    track: int | None


@dataclass(frozen=True)
class Frame:
    """One image of the package (a row of media.csv)."""

    media_id: str
    event: str  # the event folder it came from
    seq: int
    time: dt.datetime
    width: int
    height: int


def detection(body: dict[str, Any], time: dt.datetime) -> Detection | None:
    """The box of a mono_ir line, or None for a line without one (`none`: nothing seen)."""
    box = body.get("box") or []
    if len(box) != 4:
        return None
    track = body.get("track")
    return Detection(seq=int(body["seq"]), time=time, label=str(body.get("label", "")),
                     confidence=float(body.get("confidence", 0.0)),
                     box=(float(box[0]), float(box[1]), float(box[2]), float(box[3])),
                     model=str(body.get("model") or ""),
                     track=track if isinstance(track, int) else None)


def read_tracks(path: Path) -> list[dict[str, Any]] | None:
    """The finished tracks of tracks.jsonl (a malformed line skipped); None without the file."""
    if not path.is_file():
        return None
    out = []
    for raw in path.read_text(encoding="utf-8").splitlines():
        try:
            body = json.loads(raw).get("track")
        except (ValueError, AttributeError):
            continue
        if isinstance(body, dict) and isinstance(body.get("id"), int) and all(
                isinstance(body.get(k), (int, float)) for k in ("first_s", "last_s",
                                                                 "best_confidence")):
            out.append(body)
    return sorted(out, key=lambda t: (t["first_s"], t["id"]))


def best_detection(track: dict[str, Any], detections: list[Detection]) -> Detection | None:
    """The detector box the track's best view came from: its box and confidence, inside its
    time span. A box carrying the track's id wins (its first boxes, before `min_hits`
    confirmed it, carry none)."""
    lo, hi = track["first_s"] - SAME_TIME_S, track["last_s"] + SAME_TIME_S
    best = [round(float(v), 1) for v in track.get("best_box") or []]
    found = [d for d in detections
             if lo <= d.time.timestamp() <= hi and [round(v, 1) for v in d.box] == best
             and abs(d.confidence - float(track["best_confidence"])) < 5e-4
             and d.track in (None, track["id"])]
    found.sort(key=lambda d: (d.track != track["id"], d.seq))
    return found[0] if found else None


def event_id(track: dict[str, Any]) -> str:
    """The eventID of a track's observations (event- and media-level alike)."""
    return f"track-{track['id']}"


def _classified_by(models: set[str]) -> str:
    names = ", ".join(sorted(m for m in models if m))
    return f"trapflow mono_ir ({names})" if names else "trapflow mono_ir"


def _taxon(label: str, taxa: dict[str, str]) -> dict[str, Any]:
    name = taxa.get(label, "")
    return {"scientificName": name, "observationType": "animal" if name else "unclassified"}


def _measured(track: dict[str, Any]) -> tuple[dict[str, Any], str, str]:
    """Camtrap DP's position and speed fields, and the length as tags and as a comment
    (the standard has no length field)."""
    fields: dict[str, Any] = {}
    radius, angle = track.get("position_radius_m"), track.get("position_angle_deg")
    if isinstance(radius, (int, float)) and isinstance(angle, (int, float)):
        fields["individualPositionRadius"] = round(max(0.0, float(radius)), 3)
        fields["individualPositionAngle"] = round(
            max(-MAX_ANGLE_DEG, min(MAX_ANGLE_DEG, float(angle))), 1)
    speed = track.get("speed_m_s")
    if isinstance(speed, (int, float)):
        fields["individualSpeed"] = round(max(0.0, float(speed)), 3)
    length = track.get("length_m")
    if not isinstance(length, (int, float)):
        return fields, "", ""
    spread, views = track.get("length_spread_m"), track.get("length_views")
    tags = [f"length_m:{length:.3f}"]
    comment = f"length {length:.3f} m"
    if isinstance(spread, (int, float)):
        tags.append(f"length_spread_m:{spread:.3f}")
        comment += f" (spread {spread:.3f} m"
        comment += f", {views} views)" if isinstance(views, int) else ")"
    if isinstance(views, int):
        tags.append(f"length_views:{views}")
    return fields, "|".join(tags), comment


def event_row(track: dict[str, Any], dep_id: str, taxa: dict[str, str],
              models: set[str]) -> dict[str, Any]:
    """The event-level observation of one track: one animal from its first to its last
    sighting (`count` 1, so that an event-level table's counts can be summed)."""
    label = str(track.get("label", ""))
    share = track.get("label_share")
    measured, tags, length = _measured(track)
    comment = f"detector label: {label}"
    if isinstance(share, (int, float)):
        comment += f" (share {share:.2f}, {track.get('pairs', 0)} pairs)"
    return {"observationID": event_id(track), "deploymentID": dep_id, "mediaID": "",
            "eventID": event_id(track), "eventStart": iso(utc(track["first_s"])),
            "eventEnd": iso(utc(track["last_s"])), "observationLevel": "event",
            **_taxon(label, taxa), "count": 1, "individualID": str(track["id"]), **measured,
            "classificationMethod": "machine", "classifiedBy": _classified_by(models),
            "classificationTimestamp": iso(utc(track["last_s"])),
            "classificationProbability": round(float(track["best_confidence"]), 4),
            "observationTags": tags,
            "observationComments": "; ".join(c for c in (comment, length) if c)}


def media_row(det: Detection, frame: Frame, dep_id: str, taxa: dict[str, str],
              observation_id: str, event: tuple[str, str, str],
              track: dict[str, Any] | None = None) -> dict[str, Any]:
    """A media-level observation of one box in one image (eventID, eventStart, eventEnd as
    `event` gives them), normalized to the image with the top-left corner as bboxX/bboxY."""
    x1, y1, x2, y2 = det.box
    w, h = frame.width, frame.height
    x1, x2 = max(0.0, min(x1, w)), max(0.0, min(x2, w))
    y1, y2 = max(0.0, min(y1, h)), max(0.0, min(y2, h))
    row = {"observationID": observation_id, "deploymentID": dep_id,
           "mediaID": frame.media_id, "eventID": event[0], "eventStart": event[1],
           "eventEnd": event[2], "observationLevel": "media", **_taxon(det.label, taxa),
           "count": 1, "bboxX": round(x1 / w, 6), "bboxY": round(y1 / h, 6),
           "bboxWidth": round((x2 - x1) / w, 6), "bboxHeight": round((y2 - y1) / h, 6),
           "classificationMethod": "machine", "classifiedBy": _classified_by({det.model}),
           "classificationTimestamp": iso(det.time),
           "classificationProbability": round(det.confidence, 4),
           "observationComments": f"detector label: {det.label}"}
    if track is not None:
        row["individualID"] = str(track["id"])
        row["observationComments"] += "; the best view of its track"
    return row


def blank_row(frame: Frame, dep_id: str, min_confidence: float) -> dict[str, Any]:
    """A media-level blank: the detector saw no box at or above the cut in this image."""
    t = iso(frame.time)
    return {"observationID": f"{frame.media_id}-blank", "deploymentID": dep_id,
            "mediaID": frame.media_id, "eventID": frame.event, "eventStart": t, "eventEnd": t,
            "observationLevel": "media", "observationType": "blank",
            "classificationMethod": "machine", "classifiedBy": "trapflow mono_ir",
            "classificationTimestamp": t,
            "observationComments": f"no detector box with confidence >= {min_confidence:g}"}
