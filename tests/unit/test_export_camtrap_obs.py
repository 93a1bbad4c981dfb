"""Camtrap DP observation rows from tracks and boxes (trapflow.export.camtrap_obs), pure."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from trapflow.export import camtrap_obs as obs
from trapflow.export.camtrapdp import Deployment, build_rows

T0 = 1795619145.0
TAXA = {"crab": "Cancer pagurus"}


def track(**kw: Any) -> dict[str, Any]:
    return {"id": 7, "label": "crab", "label_share": 1.0, "first_s": T0, "last_s": T0 + 3.6,
            "pairs": 12, "best_confidence": 0.94, "best_box": [10.0, 20.0, 40.0, 50.0], **kw}


def det(seq: int, t_s: float, conf: float, box: tuple[float, ...], tr: int | None) -> obs.Detection:
    return obs.Detection(seq=seq, time=obs.utc(t_s), label="crab", confidence=conf,
                         box=(box[0], box[1], box[2], box[3]), model="24afdaf6", track=tr)


MEASURED = {"range_m": 1.152, "position_radius_m": 1.141, "position_angle_deg": -22.5,
            "length_m": 0.23, "length_spread_m": 0.045, "length_views": 4, "speed_m_s": 0.071}


@pytest.mark.parametrize(("extra", "want"), [
    # measured: Camtrap DP's position and speed fields, the length as tags and comment
    (MEASURED, {"individualPositionRadius": 1.141, "individualPositionAngle": -22.5,
                "individualSpeed": 0.071,
                "observationTags": "length_m:0.230|length_spread_m:0.045|length_views:4"}),
    # not measured: the fields stay out (empty cells), no tags
    ({}, {"individualPositionRadius": None, "individualSpeed": None, "observationTags": ""}),
    # an angle past Camtrap DP's -90..90 is clamped, not refused by the table schema later
    ({"position_radius_m": 0.5, "position_angle_deg": 91.0},
     {"individualPositionRadius": 0.5, "individualPositionAngle": 90.0}),
])
def test_event_row_maps_a_track(extra: dict[str, Any], want: dict[str, Any]) -> None:
    row = obs.event_row(track(**extra), "dep", TAXA, {"24afdaf6", ""})
    assert row["observationLevel"] == "event" and row["count"] == 1
    assert (row["observationID"], row["eventID"], row["individualID"]) == \
        ("track-7", "track-7", "7")
    assert (row["eventStart"], row["eventEnd"]) == ("2026-11-25T15:05:45Z",
                                                    "2026-11-25T15:05:48Z")
    assert (row["scientificName"], row["observationType"]) == ("Cancer pagurus", "animal")
    assert row["classificationProbability"] == 0.94
    assert row["classifiedBy"] == "trapflow mono_ir (24afdaf6)"
    for key, value in want.items():
        assert row.get(key) == value, key
    if "length_m" in extra:
        assert "length 0.230 m (spread 0.045 m, 4 views)" in row["observationComments"]


def test_an_unmapped_label_is_unclassified() -> None:
    row = obs.event_row(track(label="blob"), "dep", TAXA, set())
    assert (row["scientificName"], row["observationType"]) == ("", "unclassified")
    assert row["observationComments"].startswith("detector label: blob")


def test_best_detection_prefers_the_box_with_the_track_id() -> None:
    """The best box is found by box and confidence in the track's span; a copy of it outside
    the span or on another track is not it, and one carrying the track's id wins."""
    box = (10.0, 20.0, 40.0, 50.0)
    dets = [det(1, T0 - 5, 0.94, box, None),  # before the track
            det(2, T0 + 1, 0.94, box, 3),  # another track's box
            det(3, T0 + 1, 0.93, box, 7),  # another confidence
            det(4, T0 + 1, 0.94, box, None),
            det(5, T0 + 2, 0.94, box, 7)]
    found = obs.best_detection(track(), dets)
    assert found is not None and found.seq == 5
    found = obs.best_detection(track(), dets[:4])
    assert found is not None and found.seq == 4  # before confirmation: no id yet
    assert obs.best_detection(track(), dets[:3]) is None


def test_media_row_normalizes_the_box_and_blank_row() -> None:
    frame = obs.Frame("ev-4", "ev", 4, obs.utc(T0 + 1), 320, 240)
    row = obs.media_row(det(4, T0 + 1, 0.94, (-8.0, 20.0, 40.0, 300.0), 7), frame, "dep", TAXA,
                        "ev-4-0", ("track-7", "a", "b"), track())
    assert (row["bboxX"], row["bboxY"], row["bboxWidth"], row["bboxHeight"]) == \
        (0.0, round(20 / 240, 6), 0.125, round(220 / 240, 6))
    assert (row["eventID"], row["individualID"], row["mediaID"]) == ("track-7", "7", "ev-4")
    blank = obs.blank_row(frame, "dep", 0.5)
    assert (blank["observationType"], blank["observationLevel"], blank["eventID"]) == \
        ("blank", "media", "ev")
    assert blank["eventStart"] == blank["eventEnd"] == "2026-11-25T15:05:46Z"
    assert "scientificName" not in blank and "count" not in blank


def test_read_tracks_skips_malformed_lines(tmp_path: Path) -> None:
    assert obs.read_tracks(tmp_path / "none.jsonl") is None
    path = tmp_path / "tracks.jsonl"
    path.write_text("\n".join([json.dumps({"track": track(id=2, first_s=T0 + 1)}),
                               "not json", json.dumps({"track": {"id": "x"}}),
                               json.dumps({"counts": {}}), json.dumps({"track": track()})]))
    assert [t["id"] for t in obs.read_tracks(path) or []] == [7, 2]


def test_utc_and_iso_agree_with_results_labels() -> None:
    t = dt.datetime(2026, 11, 25, 15, 5, 45, 421000, tzinfo=dt.timezone.utc)
    assert obs.iso(obs.utc(t.timestamp())) == "2026-11-25T15:05:45Z"


def test_a_tracks_best_frame_has_one_row_when_two_events_hold_its_image(tmp_path: Path) -> None:
    """A pair whose left image two event folders hold (events that overlap, a restarted
    events node): media.csv lists it once (the first event's), and the track's best frame
    is one row, as Camtrap DP has one media-level row per track's best view."""
    line = {"mono_ir": {"timestamp": "2026-11-29 01:00:00.500", "seq": 5, "label": "crab",
                        "confidence": 0.9, "box": [1.0, 2.0, 11.0, 12.0], "track": 1, "v": 2}}
    (tmp_path / "results.jsonl").write_text(json.dumps(line) + "\n")
    t = dt.datetime(2026, 11, 29, 1, 0, 0, 500000, tzinfo=dt.timezone.utc).timestamp()
    track = {"id": 1, "first_s": t - 1, "last_s": t + 1, "best_confidence": 0.9,
             "best_box": [1.0, 2.0, 11.0, 12.0], "label": "crab", "pairs": 3}
    (tmp_path / "tracks.jsonl").write_text(json.dumps({"track": track}) + "\n")
    for ev in ("ev-a", "ev-b"):
        (tmp_path / "events" / ev / "left").mkdir(parents=True)
        cv2.imwrite(str(tmp_path / "events" / ev / "left" / "5.jpg"),
                    np.zeros((24, 32, 3), np.uint8))
    rows = build_rows(tmp_path, Deployment(latitude=0.0, longitude=0.0))
    assert [m["mediaID"] for m in rows.media] == ["ev-a-5"]
    frames = [o for o in rows.observations if o["observationLevel"] == "media"]
    assert [(o["eventID"], o["mediaID"]) for o in frames] == [("track-1", "ev-a-5")]
