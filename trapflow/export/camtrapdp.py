"""`trapflow export camtrapdp RUN_DIR OUT`: a run's events as a Camtrap DP 1.0 package.

Camtrap DP (the TDWG camera-trap data exchange format) is a Frictionless Data Package:
datapackage.json (profile, project, spatial, temporal, taxonomic coverage) with three CSV
tables. Here: deployments.csv holds the run as one deployment, with its location, depth and
setup from a metadata file or flags; media.csv one row per left image of each event folder
(the images are linked or copied into OUT/media/); observations.csv one media-level,
machine-classified row per detection (mono_ir) in those images, boxes normalized to the
image as Camtrap DP wants (bboxX, bboxY: top-left corner, 0..1). A run without events has
no media, so no observations either: Camtrap DP ties every observation to its media.

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


def _iso(t: dt.datetime) -> str:
    return t.strftime("%Y-%m-%dT%H:%M:%SZ")


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


def build_rows(run_dir: Path, dep: Deployment, events_folder: str = "events") -> Rows:
    """The package's rows from a run directory (results.jsonl and the event folders)."""
    # Long on purpose: a package's rows built from one reading of the run (results and
    # events), in the order its tables refer to each other (deployment, media, observations).
    run_results = _results(run_dir / "results.jsonl")
    if not (run_dir / "results.jsonl").is_file():
        raise ExportError(f"export: expected {run_dir / 'results.jsonl'} (a run directory), "
                          "found none; name the directory a pipeline ran in (its --run-dir)")
    times = {b["seq"]: _parse(b["timestamp"]) for _, b in run_results if "timestamp" in b}
    if not times:
        raise ExportError(f"export: {run_dir / 'results.jsonl'} holds no result; a run that "
                          "processed nothing has nothing to export")
    dep_id = dep.deployment_id or run_dir.name
    # Every detection of the run (an event's own results.jsonl holds only its triggers).
    detections: dict[int, list[dict[str, Any]]] = {}
    for algo, body in run_results:
        if algo == "mono_ir":
            detections.setdefault(body["seq"], []).append(body)
    start, end = min(times.values()), max(times.values())
    media: list[dict[str, Any]] = []
    observations: list[dict[str, Any]] = []
    files: list[tuple[Path, str]] = []
    labels: set[str] = set()
    for ev in sorted(p for p in (run_dir / events_folder).glob("*") if (p / "left").is_dir()):
        jpgs = sorted((ev / "left").glob("*.jpg"))
        seqs = [int(p.stem) for p in jpgs if p.stem.isdigit()]
        ev_times = [times[s] for s in seqs if s in times]
        if not ev_times:
            continue
        ev_start, ev_end = min(ev_times), max(ev_times)
        for jpg in jpgs:
            if not jpg.stem.isdigit() or int(jpg.stem) not in times:
                continue  # a pair without a result: no time to give it
            seq = int(jpg.stem)
            media_id = f"{ev.name}-{seq}"
            rel = f"media/{ev.name}/{jpg.name}"
            files.append((jpg, rel))
            media.append({"mediaID": media_id, "deploymentID": dep_id,
                          "captureMethod": "activityDetection", "timestamp": _iso(times[seq]),
                          "filePath": rel, "filePublic": "false", "fileName": jpg.name,
                          "fileMediatype": "image/jpeg"})
            width, height = _size(jpg)
            dets = detections.get(seq, [])
            for k, b in enumerate(d for d in dets if len(d.get("box") or []) == 4):
                x1, y1, x2, y2 = (float(v) for v in b["box"])
                x1, x2 = max(0.0, min(x1, width)), max(0.0, min(x2, width))
                y1, y2 = max(0.0, min(y1, height)), max(0.0, min(y2, height))
                label = str(b.get("label", ""))
                labels.add(label)
                taxon = dep.taxa.get(label, "")
                observations.append({
                    "observationID": f"{media_id}-{k}", "deploymentID": dep_id,
                    "mediaID": media_id, "eventID": ev.name, "eventStart": _iso(ev_start),
                    "eventEnd": _iso(ev_end), "observationLevel": "media",
                    "observationType": "animal" if taxon else "unclassified",
                    "scientificName": taxon, "count": 1,
                    "bboxX": round(x1 / width, 6), "bboxY": round(y1 / height, 6),
                    "bboxWidth": round((x2 - x1) / width, 6),
                    "bboxHeight": round((y2 - y1) / height, 6),
                    "classificationMethod": "machine",
                    "classifiedBy": f"trapflow mono_ir ({b['model']})" if b.get("model")
                    else "trapflow mono_ir",
                    "classificationTimestamp": _iso(times[seq]),
                    "classificationProbability": round(float(b.get("confidence", 0.0)), 4),
                    "observationComments": f"detector label: {label}"})
    deployment = {
        "deploymentID": dep_id, "locationID": dep.location_id, "locationName": dep.location_name,
        "latitude": dep.latitude, "longitude": dep.longitude,
        "deploymentStart": _iso(start), "deploymentEnd": _iso(end), "setupBy": dep.setup_by,
        "cameraModel": dep.camera_model, "cameraDepth": dep.depth_m, "cameraHeight": dep.height_m,
        "cameraTilt": dep.tilt_deg, "cameraHeading": dep.heading_deg, "habitat": dep.habitat,
        "timestampIssues": "false", "deploymentComments": dep.comments}
    return Rows([deployment], media, observations, files, start, end, labels)


def datapackage(rows: Rows, dep: Deployment, name: str) -> dict[str, Any]:
    """datapackage.json: the Camtrap DP profile's required metadata and the three resources."""
    taxa = sorted({dep.taxa[lb] for lb in rows.labels if lb in dep.taxa})
    return {
        "profile": PROFILE, "name": name, "id": name,
        "created": _iso(dt.datetime.now(dt.timezone.utc)),
        "title": dep.project,
        "contributors": [{"title": dep.contributor or dep.setup_by or "trapflow",
                          "role": "contact"}],
        "project": {"title": dep.project, "samplingDesign": "targeted",
                    "captureMethod": ["activityDetection"], "individualAnimals": False,
                    "observationLevel": ["media"]},
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


def write_package(run_dir: Path, out: Path, dep: Deployment,
                  events_folder: str = "events") -> Rows:
    """Write the package into OUT (created; refused when it exists and is not empty)."""
    dep.check()
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ExportError(f"export: OUT {out} exists and is not an empty folder; name a new one")
    rows = build_rows(run_dir, dep, events_folder)
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
