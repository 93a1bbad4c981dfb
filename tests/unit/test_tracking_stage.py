"""The normalizer's observation stage: track ids on detection lines, finished tracks with
their measured length, range, position and speed, interval counts; late results."""

from __future__ import annotations

import math
from typing import Any

import pytest

from trapflow.config.schema import ObserveConfig
from trapflow.export.report import RunSummary, observations, render_html
from trapflow.tracking.stage import Observer, View, aggregate

T0_NS = 1_764_000_000 * 10**9


def _line(x: float, conf: float = 0.9, **extra: Any) -> dict[str, Any]:
    return {"timestamp": "t", "seq": 0, "label": "crab", "confidence": conf,
            "box": [x, 100.0, x + 40.0, 130.0], **extra, "v": 2}


def test_lines_get_track_ids_and_keep_v_last() -> None:
    obs = Observer(ObserveConfig())
    firsts = [_line(100.0)]
    obs.feed(T0_NS, firsts)
    assert firsts[0]["track"] is None  # tentative until min_hits (2)
    seconds = [_line(102.0)]
    obs.feed(T0_NS + 66_000_000, seconds)
    assert seconds[0]["track"] == 1 and list(seconds[0])[-1] == "v"


def test_no_detection_lines_are_left_alone() -> None:
    none = [{"timestamp": "t", "seq": 0, "label": "none", "confidence": 0.0, "box": [], "v": 2}]
    Observer(ObserveConfig()).feed(T0_NS, none)
    assert "track" not in none[0]


def test_a_late_result_is_tracked_at_the_newest_time_and_counted() -> None:
    """Two workers answer out of capture order: the tracker must not raise."""
    obs = Observer(ObserveConfig())
    obs.feed(T0_NS + 100_000_000, [_line(100.0)])
    late = [_line(100.0)]
    obs.feed(T0_NS, late)
    assert obs.late == 1 and late[0]["track"] == 1


def test_a_finished_track_carries_its_measurements_and_counts_close() -> None:
    obs = Observer(ObserveConfig(interval_s=10.0, max_gap_s=1.0))
    for i in range(20):  # 0.3 m/s along x at 1.5 m, 0.2 m long
        t_ns = T0_NS + i * 100_000_000
        obs.feed(t_ns, [_line(100.0 + i, xyz=[0.03 * i, 0.0, 1.5], length_m=0.2,
                              length_sd_m=0.01)])
    done = obs.feed(T0_NS + 5 * 10**9, [])  # after the gap: the track has ended
    (rec,) = [t["track"] for t in done.tracks]
    assert rec["id"] == 1 and rec["pairs"] == 20
    assert rec["length_m"] == pytest.approx(0.2) and rec["length_views"] == 10
    # First measured view: the second pair (the first was the tentative track's).
    assert rec["range_m"] == pytest.approx(1.5, abs=1e-3)
    assert rec["position_angle_deg"] == pytest.approx(math.degrees(math.atan2(0.03, 1.5)),
                                                      abs=0.05)
    assert rec["speed_m_s"] == pytest.approx(0.3, rel=1e-3)
    final = obs.finish()
    counts = [c["counts"] for c in done.counts + final.counts]
    assert [lab["max_n"] for c in counts for lab in c["labels"]] == [1]


@pytest.mark.parametrize(("views", "expected"), [
    ([], {}),  # nothing measured: no keys, never zeros
    # one view: range and position, no speed (a line through one point is no speed)
    ([View(0.0, (1.0, 0.0, 1.0), 0.3, 0.02)],
     {"range_m": round(math.sqrt(2), 3), "position_radius_m": round(math.sqrt(2), 3),
      "position_angle_deg": 45.0, "length_m": 0.3, "length_spread_m": 0.0,
      "length_views": 1}),
])
def test_aggregate(views: list[View], expected: dict[str, Any]) -> None:
    assert aggregate(views) == expected


def test_the_sharpest_half_of_the_lengths_decides() -> None:
    """A few blurred views (large sd, wrong length) must not move the median."""
    views = [View(float(i), (0.0, 0.0, 1.0), 0.2, 0.01) for i in range(6)]
    views += [View(6.0 + i, (0.0, 0.0, 1.0), 0.5, 0.2) for i in range(4)]
    assert aggregate(views)["length_m"] == pytest.approx(0.2)


def test_one_label_per_track_in_tracks_counts_news_and_report() -> None:
    """Regression (issue 32): counts.jsonl, the report and the modem's news took a visit's
    label from the track's first box, tracks.jsonl and Camtrap DP its majority label; a
    crab track of 1 scallop box (its first) and 52 crab boxes became "scallop: 1 visit,
    MaxN 1". Every output now carries the label of the track's record."""
    obs = Observer(ObserveConfig(interval_s=600.0))
    got = []
    for i in range(53):
        line = {**_line(100.0 + i), "seq": i, "label": "scallop" if i == 0 else "crab"}
        got.append(obs.feed(T0_NS + i * 100_000_000, [line]))
    got.append(obs.finish())
    tracks = [t["track"] for g in got for t in g.tracks]
    counts = [c["counts"] for g in got for c in g.counts]
    news = [n for g in got for n in g.news]
    assert [(t["label"], t["pairs"]) for t in tracks] == [("crab", 53)]
    assert [[(lb["label"], lb["visits"], lb["max_n"]) for lb in c["labels"]]
            for c in counts] == [[("crab", 1, 1)]]
    assert news == [{"new_label": {"label": "crab", "time": "2025-11-24 16:00:00",
                                   "track": 1}}]
    s = RunSummary(run="r")
    observations(s, counts, tracks)
    assert {lb for per in s.counts_hour.values() for lb in per} == {"crab"}
    page = render_html(s)
    assert "scallop" not in page and "<td>crab</td><td>1</td><td>1</td>" in page
