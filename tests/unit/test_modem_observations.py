"""Observations on the acoustic link: a finished track in at most 12 bytes of body, interval
counts, the run's news (a new label, a new MaxN) in 8, and v2 detection lines (track id,
stereo measurement) in their compact kind, all round-tripping; old mono_ir records still
decode (fields only append); the news goes out before everything else."""

from __future__ import annotations

from typing import Any

import pytest

from trapflow.modem.codec import GENERIC, LinkCodec
from trapflow.tracking.counts import RunNews
from trapflow.tracking.stage import modem_counts, modem_news, modem_track

T0 = 1_795_617_060.526  # 2026-11-25


def _track(**extra: Any) -> dict[str, Any]:
    return {"track": {"id": 17, "label": "crab", "label_share": 1.0, "first_s": T0,
                      "last_s": T0 + 42.4, "pairs": 96, "best_confidence": 0.934,
                      "best_box": [1.0, 2.0, 3.0, 4.0], "path": [[T0, 1.0, 2.0]], **extra}}


@pytest.mark.parametrize(("extra", "budget"), [
    # the common case: measured, under two minutes, a label of the table
    ({"length_m": 0.184, "range_m": 1.52, "speed_m_s": 0.07}, 12),
    ({}, 9),  # not measured: fewer fields, fewer bytes
    ({"length_m": 0.184}, 12),  # part measured: the others say none
])
def test_a_finished_track_is_small_and_round_trips(extra: dict[str, Any], budget: int) -> None:
    codec = LinkCodec()
    rec = modem_track(_track(**extra))
    data = codec.encode(rec)
    assert data[0] != GENERIC and len(data) - 1 <= budget, len(data)
    assert codec.decode(data) == rec


def test_interval_counts_round_trip() -> None:
    codec = LinkCodec()
    rec = modem_counts({"counts": {"start_s": 1_795_617_000.0, "end_s": 1_795_617_600.0,
                                   "pairs": 9000, "labels": [
                                       {"label": "crab", "visits": 3, "max_n": 2,
                                        "dwell_s": 81.4},
                                       {"label": "sea-pen", "visits": 1, "max_n": 1,
                                        "dwell_s": 5.0}]}})
    data = codec.encode(rec)
    assert data[0] != GENERIC
    back = codec.decode(data)
    assert back["counts"]["minutes"] == 10 and back["counts"]["pairs"] == 9000
    assert [(lab["label"], lab["max_n"], lab["dwell_s"]) for lab in back["counts"]["labels"]] \
        == [("crab", 2, 81), ("sea-pen", 1, 5)]


@pytest.mark.parametrize(("news", "kinds"), [
    # a label's first track, alone at its capture time
    (RunNews(label="crab", max_n=1, new_label=True, track=3, t_s=T0), [9]),
    # first seen two at once: the new label and the run's MaxN
    (RunNews(label="urchin", max_n=2, new_label=True, track=12, t_s=T0), [9, 10]),
    # a new MaxN of a known label, off the label table
    (RunNews(label="sea-pen", max_n=4, new_label=False, track=40,
             t_s=T0), [10]),
])
def test_news_is_small_and_round_trips(news: RunNews, kinds: list[int]) -> None:
    codec = LinkCodec()
    recs = modem_news(news)
    assert [codec.encode(r)[0] for r in recs] == kinds
    for rec in recs:
        data = codec.encode(rec)
        on_table = news.label != "sea-pen"
        assert len(data) - 1 <= (8 if on_table else 8 + len(news.label)), len(data)
        assert codec.decode(data) == rec
    assert recs[0][next(iter(recs[0]))]["time"] == "2026-11-25 14:31:00"


@pytest.mark.parametrize(("hexbytes", "record"), [
    # kind 7, a finished track, as a box sent it before kinds 9 and 10 were appended
    ("071f1101a4a0ec672aba", {"track": {"id": 17, "label": "crab",
                                        "start": "2026-11-25 14:31:00", "duration_s": 42,
                                        "confidence": 0.93}}),
    # kind 8, interval counts, likewise
    ("080fe89fec670aa8460101030251", {"counts": {
        "start": "2026-11-25 14:30:00", "minutes": 10, "pairs": 9000,
        "labels": [{"label": "crab", "visits": 3, "max_n": 2, "dwell_s": 81}]}}),
])
def test_old_kinds_still_decode_beside_the_news(hexbytes: str, record: dict[str, Any]) -> None:
    """Kinds only append: bytes of the older observation kinds decode as before."""
    assert LinkCodec().decode(bytes.fromhex(hexbytes)) == record


@pytest.mark.parametrize("line", [
    # v2: tracked and measured
    {"timestamp": "2026-11-25 14:32:55.075", "seq": 0, "label": "crab", "confidence": 0.28,
     "box": [1196.8, 454.2, 1274.1, 547.6], "range_m": 1.337, "range_sd_m": 0.008,
     "length_m": 0.134, "length_sd_m": 0.008, "xyz": [0.724, 0.171, -1.111],
     "disparity_px": 98.73, "length_method": "endpoints", "model": "24afdaf6", "track": 3,
     "v": 2},
    # v2: not yet confirmed, not measured
    {"timestamp": "2026-11-25 14:32:55.075", "seq": 1, "label": "crab", "confidence": 0.5,
     "box": [1.0, 2.0, 3.0, 4.0], "unmeasured": "out_of_view", "track": None, "v": 2},
    # v1, as an older box sent it
    {"timestamp": "2025-07-07 12:52:43.120", "seq": 7, "label": "crab", "confidence": 0.71,
     "box": [5.4, 7.8, 15.6, 18.1], "v": 1},
])
def test_detection_lines_keep_their_compact_kind(line: dict[str, Any]) -> None:
    codec = LinkCodec()
    data = codec.encode({"mono_ir": line})
    assert data[0] != GENERIC
    assert codec.decode(data) == {"mono_ir": line}


def test_observations_overtake_queued_detections() -> None:
    """With the default priorities, the news (a new label, a new MaxN), then a count and a
    track, made after a backlog of detections, go out in the next frame, in that order,
    ahead of every older detection."""
    from trapflow.config.modem import ModemConfig
    from trapflow.modem.outbox import Stored
    from trapflow.modem.schedule import ClassQueue, Queued, Schedule, SendData

    cfg = ModemConfig(max_frame_payload=96, window=4, bit_rate=300.0)
    codec = LinkCodec()

    def queue(cls: str, records: list[tuple[int, dict[str, Any]]]) -> ClassQueue:
        q = ClassQueue(cls, cfg.priority_of(cls))
        for seq, rec in records:
            body = codec.encode(rec)
            q.queue.append(Queued(Stored(seq=seq, t_ns=0, cls=cls, body=body, intact=True),
                                  body))
        return q

    det = {"mono_ir": {"timestamp": "2026-11-25 14:32:55.075", "seq": 1, "label": "crab",
                       "confidence": 0.5, "box": [1.0, 2.0, 3.0, 4.0], "track": 1, "v": 2}}
    detections = queue("mono_ir/crab", [(seq, det) for seq in range(1, 41)])
    tracks = queue("track", [(41, modem_track(_track(length_m=0.2, range_m=1.5)))])
    counts = queue("counts", [(42, modem_counts({"counts": {
        "start_s": T0, "end_s": T0 + 600, "pairs": 10,
        "labels": [{"label": "crab", "visits": 1, "max_n": 1, "dwell_s": 42.0}]}}))])
    news = [modem_news(RunNews(label="fish", max_n=2, new_label=True, track=9, t_s=T0 + 9))]
    new_label = queue("new_label", [(43, news[0][0])])
    new_max_n = queue("new_max_n", [(44, news[0][1])])
    decision = Schedule(cfg, b"\x01\x02\x03\x04", []).next(
        100.0, 0, [], 0, [detections, tracks, counts, new_max_n, new_label], 44)
    assert isinstance(decision, SendData)
    sent = [q.name for q, _ in decision.batch]
    assert sent[:4] == ["new_label", "new_max_n", "counts", "track"]
