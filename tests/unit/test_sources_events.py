"""Event capture with real JPEGs: pre/post roll, overlap merging, quota deletion."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import msgspec
import numpy as np
import pytest

from trapflow.config.schema import EventsConfig, TriggerRule
from trapflow.events.clips import EventCapture, fires
from trapflow.wire.messages import StereoPair

PERIOD = 100_000_000  # 10 Hz


def pair(seq: int) -> tuple[StereoPair, bytes, bytes]:
    img = np.full((24, 32, 3), seq % 256, np.uint8)
    jpg = cv2.imencode(".jpg", img)[1].tobytes()
    t = 10**9 + seq * PERIOD
    h = StereoPair(seq=seq, t_wall_ns=t, t_mono_ns=t, t_left_ns=t, t_right_ns=t, skew_ns=0,
                   encoding="jpeg", width=32, height=24)
    return h, jpg, jpg


def crab(seq: int, conf: float = 0.8) -> dict[str, object]:
    return {"mono_ir": {"seq": seq, "label": "crab", "confidence": conf, "box": [1, 2, 3, 4]}}


CFG = EventsConfig(enabled=True, pre_s=0.2, post_s=0.2,
                   triggers=[TriggerRule(algorithm="mono_ir", label="crab", min_confidence=0.6),
                             TriggerRule(algorithm="stereo_ir", not_label="none")])


def run(cap: EventCapture, n: int, triggers: dict[int, dict[str, object]]) -> None:
    for seq in range(n):
        cap.on_pair(*pair(seq))
        if seq in triggers:
            cap.on_result(triggers[seq])
    cap.close()


def saved(folder: Path) -> list[int]:
    return sorted(int(p.stem) for p in (folder / "left").glob("*.jpg"))


def test_pre_and_post_roll_and_overlap_merge(tmp_path: Path) -> None:
    cap = EventCapture(CFG, tmp_path)
    run(cap, 40, {10: crab(10), 12: crab(12), 30: {"stereo_ir": {"seq": 30, "label": "scallop",
                                                                 "confidence": 0.9}}})
    events = sorted(p for p in tmp_path.iterdir())
    assert len(events) == 2 and cap.events_written == 2
    assert saved(events[0]) == [8, 9, 10, 11, 12, 13, 14]  # 12 extended the event to 14
    assert saved(events[1]) == [28, 29, 30, 31, 32]
    info = json.loads((events[0] / "event.json").read_text())
    assert info == {"pairs": 7, "first_seq": 8, "last_seq": 14, "results": 2}
    lines = (events[0] / "results.jsonl").read_text().splitlines()
    assert [json.loads(x)["mono_ir"]["seq"] for x in lines] == [10, 12]
    img = cv2.imread(str(events[0] / "right" / "00000010.jpg"))
    assert img is not None and abs(float(img.mean()) - 10) < 3


@pytest.mark.parametrize(
    ("result", "fired"),
    [
        (crab(1, 0.6), True),
        (crab(1, 0.59), False),
        ({"mono_ir": {"seq": 1, "detections": [{"label": "crab", "confidence": 0.7}]}}, True),
        ({"stereo_ir": {"seq": 1, "label": "none", "confidence": 0.99}}, False),
        ({"stereo_ir": {"seq": 1, "label": "scallop", "confidence": 0.1}}, True),
        ({"tags": {"seq": 1, "tags": []}}, False),
    ],
)
def test_trigger_rules(result: dict[str, object], fired: bool) -> None:
    assert any(fires(r, result) is not None for r in CFG.triggers) == fired


def test_quota_deletes_oldest_events(tmp_path: Path) -> None:
    one = len(pair(0)[1]) * 2 * 5  # bytes of one 5-pair event, roughly
    cfg = msgspec.structs.replace(CFG, quota_bytes=int(one * 2.5), min_free_bytes=0)
    cap = EventCapture(cfg, tmp_path)
    run(cap, 100, {s: crab(s) for s in (10, 30, 50, 70, 90)})
    kept = sorted(tmp_path.iterdir())
    assert cap.events_written == 5 and cap.events_deleted >= 2
    assert 1 <= len(kept) <= 3
    assert [saved(p)[2] for p in kept] == [10, 30, 50, 70, 90][-len(kept):]  # newest survive
    assert sum(f.stat().st_size for f in tmp_path.rglob("*") if f.is_file()) <= cfg.quota_bytes
    assert saved(kept[-1]) == [88, 89, 90, 91, 92]


def test_disabled_never_fires(tmp_path: Path) -> None:
    cap = EventCapture(msgspec.structs.replace(CFG, enabled=False), tmp_path)
    run(cap, 20, {5: crab(5)})
    assert list(tmp_path.iterdir()) == []


def test_a_trigger_before_any_pair_keeps_the_post_roll_from_the_first_pair(
        tmp_path: Path) -> None:
    """Regression: a result that reached the events node before any pair (its image tap
    connected later than its results tap on a loaded machine) opened an event ending at
    time 0 + post_s, which the first pair closed, empty: the run's first event folder held
    no image (seen in full-suite runs). Its post-roll now counts from the first pair."""
    cap = EventCapture(CFG, tmp_path)
    assert cap.on_result(crab(3))
    for seq in range(3, 12):
        cap.on_pair(*pair(seq))
    cap.close()
    (ev,) = sorted(tmp_path.iterdir())
    assert saved(ev) == [3, 4, 5]  # the first pair and 0.2 s after it at 10 Hz
    assert json.loads((ev / "event.json").read_text())["pairs"] == 3
