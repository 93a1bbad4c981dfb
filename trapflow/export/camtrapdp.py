"""`trapflow export camtrapdp RUN_DIR OUT`: a run's observations as a Camtrap DP 1.0 package.

Camtrap DP (the TDWG camera-trap data exchange format) is a Frictionless Data Package:
datapackage.json (profile, project, spatial, temporal, taxonomic coverage) with three CSV
tables. Here: deployments.csv holds the run as one deployment, with its location, depth and
setup from a metadata file or flags; media.csv one row per left image of each event folder
(the images are linked or copied into OUT/media/); observations.csv one event-level row per
track of tracks.jsonl (the animal from its first to its last sighting, with its stereo
position, speed and length), the media-level row of each track's best frame, and a blank
per image without a box (camtrap_obs.py builds the rows). Boxes are normalized to the image
as Camtrap DP wants (bboxX, bboxY: top-left corner, 0..1).

build_rows is pure (run files in, rows out); write_package writes the files.
"""

from __future__ import annotations

import csv
import datetime as dt
import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from trapflow.errors import TrapflowError
from trapflow.export import camtrap_obs as obs

VERSION = "1.0.1"
_BASE = f"https://raw.githubusercontent.com/tdwg/camtrap-dp/{VERSION}"
PROFILE = f"{_BASE}/camtrap-dp-profile.json"
SCHEMAS = {t: f"{_BASE}/{t}-table-schema.json" for t in ("deployments", "media", "observations")}

DEPLOYMENT_FIELDS = (
    "deploymentID", "locationID", "locationName", "latitude", "longitude",
    "coordinateUncertainty", "deploymentStart", "deploymentEnd", "setupBy", "cameraID",
    "cameraModel", "cameraDelay", "cameraHeight", "cameraDepth", "cameraTilt", "cameraHeading",
    "detectionDistance", "timestampIssues", "baitUse", "featureType", "habitat",
    "deploymentGroups", "deploymentTags", "deploymentComments")
MEDIA_FIELDS = ("mediaID", "deploymentID", "captureMethod", "timestamp", "filePath",
                "filePublic", "fileName", "fileMediatype", "exifData", "favorite",
                "mediaComments")
OBSERVATION_FIELDS = (
    "observationID", "deploymentID", "mediaID", "eventID", "eventStart", "eventEnd",
    "observationLevel", "observationType", "cameraSetupType", "scientificName", "count",
    "lifeStage", "sex", "behavior", "individualID", "individualPositionRadius",
    "individualPositionAngle", "individualSpeed", "bboxX", "bboxY", "bboxWidth", "bboxHeight",
    "classificationMethod", "classifiedBy", "classificationTimestamp",
    "classificationProbability", "observationTags", "observationComments")


class ExportError(TrapflowError):
    """A run cannot be exported: no run, missing metadata, an unwritable OUT."""


@dataclass
class Deployment:
    """Where and how the trap was deployed (Camtrap DP's deployment and project metadata)."""

    latitude: float
    longitude: float
    deployment_id: str = ""  # default: the run directory's name
    location_name: str = ""
    location_id: str = ""
    depth_m: float | None = None  # cameraDepth: metres below the surface
    height_m: float | None = None  # cameraHeight: metres above the sea floor
    tilt_deg: int | None = None
    heading_deg: int | None = None
    setup_by: str = ""
    habitat: str = ""
    camera_model: str = "trapflow-stereo"
    comments: str = ""
    project: str = "trapflow deployment"
    contributor: str = ""
    taxa: dict[str, str] = field(default_factory=dict)  # label -> scientific name

    def check(self) -> None:
        """ExportError naming the first value Camtrap DP would reject."""
        checks = [("latitude", self.latitude, -90, 90), ("longitude", self.longitude, -180, 180),
                  ("tilt", self.tilt_deg, -90, 90), ("heading", self.heading_deg, 0, 360),
                  ("depth", self.depth_m, 0, None), ("height", self.height_m, 0, None)]
        for name, v, lo, hi in checks:
            if v is None:
                continue
            if not isinstance(v, (int, float)) or v < lo or (hi is not None and v > hi):
                span = f"{lo}..{hi}" if hi is not None else f">= {lo}"
                raise ExportError(f"deployment {name}: expected a number in {span}, got {v!r}; "
                                  f"fix --{name} or `{name}` in the metadata file")


def _parse(label: str) -> dt.datetime:
    return dt.datetime.strptime(label, "%Y-%m-%d %H:%M:%S.%f").replace(tzinfo=dt.timezone.utc)


def _results(path: Path) -> list[tuple[str, dict[str, Any]]]:
    out = []
    if path.is_file():
        for raw in path.read_text(encoding="utf-8").splitlines():
            try:
                (algo, body), = json.loads(raw).items()
            except (ValueError, AttributeError):
                continue
            if isinstance(body, dict) and isinstance(body.get("seq"), int):
                out.append((algo, body))
    return out


def _size(jpg: Path) -> tuple[int, int]:
    img = cv2.imdecode(np.fromfile(str(jpg), np.uint8), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise ExportError(f"{jpg}: expected a JPEG image, got an unreadable file; remove it "
                          "or the event folder")
    return int(img.shape[1]), int(img.shape[0])


def _media(events: Path, times: dict[int, dt.datetime],
           dep_id: str) -> tuple[list[dict[str, Any]], list[obs.Frame], list[tuple[Path, str]]]:
    """media.csv's rows: the left image of every pair with a result in the event folders,
    once per pair: a pair two event folders hold (events that overlap) is the first's, so
    its boxes are not counted twice."""
    media: list[dict[str, Any]] = []
    frames: list[obs.Frame] = []
    files: list[tuple[Path, str]] = []
    listed: set[int] = set()
    for ev in sorted(p for p in events.glob("*") if (p / "left").is_dir()):
        for jpg in sorted((ev / "left").glob("*.jpg")):
            if not jpg.stem.isdigit() or int(jpg.stem) not in times:
                continue  # a pair without a result: no time to give it
            seq = int(jpg.stem)
            if seq in listed:
                continue
            listed.add(seq)
            media_id = f"{ev.name}-{seq}"
            rel = f"media/{ev.name}/{jpg.name}"
            files.append((jpg, rel))
            media.append({"mediaID": media_id, "deploymentID": dep_id,
                          "captureMethod": "activityDetection",
                          "timestamp": obs.iso(times[seq]), "filePath": rel,
                          "filePublic": "false", "fileName": jpg.name,
                          "fileMediatype": "image/jpeg"})
            frames.append(obs.Frame(media_id, ev.name, seq, times[seq], *_size(jpg)))
    return media, frames, files


@dataclass
class Rows:
    """The three tables and what datapackage.json says about them."""

    deployments: list[dict[str, Any]]
    media: list[dict[str, Any]]
    observations: list[dict[str, Any]]
    files: list[tuple[Path, str]]  # (source image, path inside the package)
    start: dt.datetime
    end: dt.datetime
    labels: set[str]


def build_rows(run_dir: Path, dep: Deployment, events_folder: str = "events", *,
               min_confidence: float = 0.0, tracks_file: str = "tracks.jsonl") -> Rows:
    """The package's rows from a run directory (results.jsonl, tracks.jsonl, the event
    folders): observations at or above min_confidence, blanks for the images below it."""
    run_results = _results(run_dir / "results.jsonl")
    if not (run_dir / "results.jsonl").is_file():
        raise ExportError(f"export: expected {run_dir / 'results.jsonl'} (a run directory), "
                          "found none; name the directory a pipeline ran in (its --run-dir)")
    times = {b["seq"]: _parse(b["timestamp"]) for _, b in run_results if "timestamp" in b}
    if not times:
        raise ExportError(f"export: {run_dir / 'results.jsonl'} holds no result; a run that "
                          "processed nothing has nothing to export")
    dep_id = dep.deployment_id or run_dir.name
    # Every box of the run (an event's own results.jsonl holds only its triggers).
    boxes = [d for algo, b in run_results if algo == "mono_ir" and b["seq"] in times
             for d in [obs.detection(b, times[b["seq"]])] if d is not None]
    media, frames, files = _media(run_dir / events_folder, times, dep_id)
    tracks = obs.read_tracks(run_dir / tracks_file)
    observations, labels, best = _event_rows(tracks or [], boxes, dep, dep_id, min_confidence)
    by_seq: dict[int, list[obs.Detection]] = {}
    for d in boxes:
        by_seq.setdefault(d.seq, []).append(d)
    spans = _spans(frames)
    framed: set[int] = set()  # tracks whose best frame has its row
    for f in frames:
        kept = [d for d in by_seq.get(f.seq, []) if d.confidence >= min_confidence]
        if not kept:
            observations.append(obs.blank_row(f, dep_id, min_confidence))
        elif tracks is not None:  # the best frame of each track, linked to its event
            for k, (d, track) in enumerate(best.get(f.seq, [])):
                # Once per track: a pair whose image two event folders hold (events that
                # overlap, a restarted events node) is the track's best frame in the first.
                if track["id"] in framed:
                    continue
                framed.add(track["id"])
                observations.append(obs.media_row(
                    d, f, dep_id, dep.taxa, f"{f.media_id}-{k}",
                    (obs.event_id(track), obs.iso(f.time), obs.iso(f.time)), track))
        else:  # no tracking in this run: every box of the image
            for k, d in enumerate(kept):
                labels.add(d.label)
                observations.append(obs.media_row(
                    d, f, dep_id, dep.taxa, f"{f.media_id}-{k}",
                    (f.event, obs.iso(spans[f.event][0]), obs.iso(spans[f.event][1]))))
    # The deployment spans the results and the tracks: a results.jsonl cut short (said by
    # run_files.damage) must not end it before tracks that went on.
    spanned = [*times.values(), *(obs.utc(t[k]) for t in tracks or [] for k in ("first_s",
                                                                               "last_s"))]
    start, end = min(spanned), max(spanned)
    return Rows([_deployment_row(dep, dep_id, start, end)], media, observations, files, start,
                end, labels)


def _event_rows(tracks: list[dict[str, Any]], boxes: list[obs.Detection], dep: Deployment,
                dep_id: str, min_confidence: float
                ) -> tuple[list[dict[str, Any]], set[str],
                           dict[int, list[tuple[obs.Detection, dict[str, Any]]]]]:
    """The event-level row of each track at or above min_confidence, the labels they carry,
    and each one's best detection by its seq (the media-level rows come from those)."""
    observations: list[dict[str, Any]] = []
    labels: set[str] = set()
    best: dict[int, list[tuple[obs.Detection, dict[str, Any]]]] = {}
    for track in tracks:
        if track["best_confidence"] < min_confidence:
            continue
        models = {d.model for d in boxes if d.track == track["id"]}
        observations.append(obs.event_row(track, dep_id, dep.taxa, models))
        labels.add(str(track.get("label", "")))
        found = obs.best_detection(track, boxes)
        if found is not None:
            best.setdefault(found.seq, []).append((found, track))
    return observations, labels, best


def _spans(frames: list[obs.Frame]) -> dict[str, tuple[dt.datetime, dt.datetime]]:
    """Each event folder's first and last image time."""
    spans: dict[str, tuple[dt.datetime, dt.datetime]] = {}
    for f in frames:
        first, last = spans.get(f.event, (f.time, f.time))
        spans[f.event] = (min(first, f.time), max(last, f.time))
    return spans


def _deployment_row(dep: Deployment, dep_id: str, start: dt.datetime,
                    end: dt.datetime) -> dict[str, Any]:
    """The package's one deployments.csv row."""
    return {
        "deploymentID": dep_id, "locationID": dep.location_id, "locationName": dep.location_name,
        "latitude": dep.latitude, "longitude": dep.longitude,
        "deploymentStart": obs.iso(start), "deploymentEnd": obs.iso(end), "setupBy": dep.setup_by,
        "cameraModel": dep.camera_model, "cameraDepth": dep.depth_m, "cameraHeight": dep.height_m,
        "cameraTilt": dep.tilt_deg, "cameraHeading": dep.heading_deg, "habitat": dep.habitat,
        "timestampIssues": "false", "deploymentComments": dep.comments}


def datapackage(rows: Rows, dep: Deployment, name: str) -> dict[str, Any]:
    """datapackage.json: the Camtrap DP profile's required metadata and the three resources."""
    taxa = sorted({dep.taxa[lb] for lb in rows.labels if lb in dep.taxa})
    return {
        "profile": PROFILE, "name": name, "id": name,
        "created": obs.iso(dt.datetime.now(dt.timezone.utc)),
        "title": dep.project,
        "contributors": [{"title": dep.contributor or dep.setup_by or "trapflow",
                          "role": "contact"}],
        "project": {"title": dep.project, "samplingDesign": "targeted",
                    "captureMethod": ["activityDetection"], "individualAnimals": False,
                    "observationLevel": sorted({r["observationLevel"]
                                                for r in rows.observations}) or ["media"]},
        "spatial": {"type": "Point", "coordinates": [dep.longitude, dep.latitude]},
        "temporal": {"start": rows.start.date().isoformat(), "end": rows.end.date().isoformat()},
        "taxonomic": [{"scientificName": t} for t in taxa],
        "resources": [{"name": t, "path": f"{t}.csv", "profile": "tabular-data-resource",
                       "format": "csv", "mediatype": "text/csv", "encoding": "utf-8",
                       "schema": SCHEMAS[t]} for t in ("deployments", "media", "observations")],
    }


def _csv(path: Path, fields: tuple[str, ...], rows: list[dict[str, Any]]) -> None:
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=fields, extrasaction="raise", lineterminator="\n")
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r.get(k) is None else r.get(k, "")) for k in fields})


def write_package(run_dir: Path, out: Path, dep: Deployment, events_folder: str = "events",
                  *, min_confidence: float = 0.0, tracks_file: str = "tracks.jsonl") -> Rows:
    """Write the package into OUT (created; refused when it exists and is not empty)."""
    dep.check()
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ExportError(f"export: OUT {out} exists and is not an empty folder; name a new one")
    rows = build_rows(run_dir, dep, events_folder, min_confidence=min_confidence,
                      tracks_file=tracks_file)
    try:
        out.mkdir(parents=True, exist_ok=True)
        for src, rel in rows.files:
            dst = out / rel
            dst.parent.mkdir(parents=True, exist_ok=True)
            try:
                os.link(src, dst)
            except OSError:
                shutil.copyfile(src, dst)
        _csv(out / "deployments.csv", DEPLOYMENT_FIELDS, rows.deployments)
        _csv(out / "media.csv", MEDIA_FIELDS, rows.media)
        _csv(out / "observations.csv", OBSERVATION_FIELDS, rows.observations)
        name = "".join(c if c.isalnum() or c in "-_." else "-" for c in
                       (dep.deployment_id or run_dir.name).lower())
        (out / "datapackage.json").write_text(
            json.dumps(datapackage(rows, dep, name), indent=2) + "\n", encoding="utf-8")
    except OSError as exc:
        raise ExportError(f"export: cannot write {out}: {exc.strerror}; name a writable OUT") \
            from None
    return rows
