"""The viewer's preview and what the page draws on it, with no sockets: when the broker
publishes a preview (only while a page asks), the preview's images and wire form, and the
state's track ids, measurements, live counts, motion regions and gated pools."""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import msgspec
import numpy as np
import pytest

from tests.builders import image, jpeg, pair_header, result
from trapflow.broker.preview import PreviewClock, drawn_pools
from trapflow.errors import ProtocolError
from trapflow.normalizer.result_json import dumps, normalize
from trapflow.viewer.state import LiveCounts, ViewState
from trapflow.wire import jpeg as wire_jpeg
from trapflow.wire import messages, tap_msgs


@dataclass
class _Pool:
    plugin: str = ""


def test_drawn_pools_by_plugin_or_name() -> None:
    pools = {"mono": _Pool(), "stereo": _Pool(), "vo": _Pool(), "fish": _Pool("mono"),
             "tags": _Pool(), "mine": _Pool("pkg.mod:Thing")}
    assert drawn_pools(pools) == {"mono", "fish", "tags"}


# Each row: events in order, (what, pool or "", now), and whether each gave a preview.
# interval 0.5 s; drawn pool "mono".
PREVIEW_ROWS = [
    # No page open: nothing, whatever arrives or is dispatched (the budget with no page).
    ([("arrive", "", 0.0), ("dispatch", "mono", 0.1), ("arrive", "", 5.0)],
     [False, False, False], False),
    # A page opens: the first drawn dispatch is the preview at once, the next only after
    # the interval; pairs that merely arrive meanwhile are no preview.
    ([("want", "", 1.0), ("arrive", "", 1.0), ("dispatch", "mono", 1.05),
      ("dispatch", "mono", 1.3), ("arrive", "", 1.4), ("dispatch", "mono", 1.56)],
     [False, True, False, False, True], True),
    # A pool that draws nothing (stereo, vo) never gives the preview while mono is due soon.
    ([("want", "", 0.0), ("dispatch", "stereo", 0.0), ("dispatch", "vo", 0.2),
      ("dispatch", "mono", 0.3)],
     [False, False, True], True),
    # Mono takes nothing (gated, switched off): after an extra interval an arrival is taken.
    ([("want", "", 0.0), ("arrive", "", 0.4), ("arrive", "", 0.5), ("arrive", "", 0.7),
      ("arrive", "", 1.0), ("arrive", "", 1.2)],
     [False, True, False, False, False], True),
    # The page closed (the viewer unsubscribed): nothing more.
    ([("want", "", 0.0), ("dispatch", "mono", 0.0), ("unwant", "", 0.1),
      ("dispatch", "mono", 2.0), ("arrive", "", 9.0)],
     [True, False, False], False),
]


@pytest.mark.parametrize(("events", "expected", "wanted_at_end"), PREVIEW_ROWS)
def test_preview_clock(events: list[tuple[str, str, float]], expected: list[bool],
                       wanted_at_end: bool) -> None:
    clock = PreviewClock(0.5, {"mono"})
    got = []
    for what, pool, now in events:
        if what in ("want", "unwant"):
            clock.want(what == "want", now)
        elif what == "arrive":
            got.append(clock.on_arrival(now))
        else:
            got.append(clock.on_dispatch(pool, now))
    assert got == expected
    assert clock.published == sum(expected) and clock.wanted == wanted_at_end


def test_preview_clock_without_drawn_pools_takes_arrivals_at_the_rate() -> None:
    clock = PreviewClock(0.5, ())
    clock.want(True, 0.0)
    assert [clock.on_arrival(t) for t in (0.0, 0.2, 0.5, 0.6, 1.0)] == [
        True, False, True, False, True]
    with pytest.raises(ValueError, match="expected more than 0 s"):
        PreviewClock(0.0, ())


def test_raw_preview_is_reduced_to_the_page_width() -> None:
    img = image(1280, 720, seed=3)
    img[200:400, 300:700] = (0, 0, 255)
    h = pair_header(1, 1280, 720, encoding="raw")
    left, right = wire_jpeg.preview_pair(h, img.tobytes(), img.tobytes())
    out = cv2.imdecode(np.frombuffer(left, np.uint8), cv2.IMREAD_COLOR)
    assert out.shape == (360, 640, 3)
    assert out[150, 250, 2] > 200 and out[150, 250, :2].max() < 60  # the red block, halved
    assert len(left) < img.nbytes / 20 and right[:2] == b"\xff\xd8"


def test_small_raw_and_jpeg_previews() -> None:
    img = image(320, 240, seed=1)
    left, _ = wire_jpeg.preview_pair(pair_header(2, 320, 240, "raw"), img.tobytes(),
                                     img.tobytes())
    assert cv2.imdecode(np.frombuffer(left, np.uint8), cv2.IMREAD_COLOR).shape == (240, 320, 3)
    data = jpeg(img)
    assert wire_jpeg.preview_pair(pair_header(3, 320, 240), data, data) == (data, data)


@pytest.mark.parametrize(("left", "error"), [
    (b"", "left image as JPEG of 1.."),
    (b"GIF89a", "left image as JPEG"),
    (b"\xff\xd8" + b"x" * tap_msgs.MAX_PREVIEW_BYTES, "left image as JPEG"),
])
def test_preview_message_rejected(left: bytes, error: str) -> None:
    header = messages.encode(pair_header(4))
    with pytest.raises(ProtocolError, match=error):
        tap_msgs.decode_tap([tap_msgs.TOPIC_PREVIEW, header, left, b"\xff\xd8ok"])


def test_preview_message_carries_the_motion_regions() -> None:
    h = msgspec.structs.replace(pair_header(5, 1280, 720), motion=True, motion_score=0.02,
                                motion_regions=((10, 20, 110, 220), (0, 0, 16, 16)))
    msg = tap_msgs.decode_tap([tap_msgs.TOPIC_PREVIEW, messages.encode(h), b"\xff\xd8L",
                               b"\xff\xd8R"])
    assert isinstance(msg, tap_msgs.TapPreview)
    assert msg.header.motion_regions == ((10, 20, 110, 220), (0, 0, 16, 16))
    st = ViewState()
    st.on_image(msg.header, msg.left, msg.right)
    assert st.tick(1.0)
    frame = st.snapshot(1.0)["frame"]
    assert frame["motion"] == [[10, 20, 110, 220], [0, 0, 16, 16]]
    assert (frame["width"], frame["height"]) == (1280, 720)  # boxes refer to the full frame


def _det_lines(seq: int, t_ns: int, dets: list[messages.Detection],
               tracks: list[int | None]) -> list[tuple[str, dict]]:
    res = result(messages.MonoIR(detections=dets), seq=seq, t_wall_ns=t_ns, pool="mono")
    out = []
    for obj, track in zip(normalize(res), tracks, strict=True):
        obj["mono_ir"]["track"] = track  # as the normalizer's observation stage sets it
        out.append(messages.decode_result_line(dumps(obj)))
    return out


def test_detections_carry_track_and_measurement_to_the_page() -> None:
    st = ViewState()
    now_ns = time.time_ns()
    st.on_image(pair_header(8), b"\xff\xd8L", b"\xff\xd8R")
    dets = [messages.Detection(label="crab", confidence=0.9, box=(1, 2, 30, 40),
                               range_m=1.234, range_sd_m=0.02, xyz=(0.1, 0.2, 1.2),
                               disparity_px=40.0, length_m=0.31, length_sd_m=0.01,
                               length_method="box"),
            messages.Detection(label="fish", confidence=0.6, box=(40, 2, 60, 20),
                               unmeasured="textureless")]
    for kind, fields in _det_lines(8, now_ns, dets, [12, None]):
        st.on_result(kind, fields, now_ns / 1e9)
    assert st.tick(1.0)
    got = st.snapshot(1.0)["frame"]["detections"]
    assert got[0]["track"] == 12 and got[0]["range_m"] == 1.234
    assert (got[0]["range_sd_m"], got[0]["length_m"], got[0]["length_sd_m"]) == (
        0.02, 0.31, 0.01)
    assert got[0]["length_method"] == "box" and "unmeasured" not in got[0]
    assert got[1]["track"] is None and got[1]["unmeasured"] == "textureless"
    assert "range_m" not in got[1] and "xyz" not in got[1]


# Each row: detections (t_s, seq, label, track) fed in order -> (start_s, {label: (visits,
# MaxN)}). Interval 600 s, aligned to multiples of it.
COUNT_ROWS = [
    # Two crabs together in one pair: 2 visits, MaxN 2; a fish alone.
    ([(1200.0, 1, "crab", 1), (1200.0, 1, "crab", 2), (1201.0, 2, "crab", 1),
      (1202.0, 3, "fish", 3)], 1200.0, {"crab": (2, 2), "fish": (1, 1)}),
    # One crab seen in many pairs is one visit, MaxN 1.
    ([(1200.0 + i, i, "crab", 5) for i in range(10)], 1200.0, {"crab": (1, 1)}),
    # A new interval starts afresh; the track that goes on is no new visit there, a late
    # line of the closed interval changes nothing.
    ([(1799.0, 1, "crab", 1), (1799.0, 1, "crab", 2), (1800.0, 2, "crab", 1),
      (1799.5, 3, "crab", 9), (1801.0, 4, "crab", 4)], 1800.0, {"crab": (1, 1)}),
]


@pytest.mark.parametrize(("dets", "start", "expected"), COUNT_ROWS)
def test_live_counts(dets: list[tuple[float, int, str, int]], start: float,
                     expected: dict[str, tuple[int, int]]) -> None:
    c = LiveCounts(600.0)
    for t_s, seq, label, track in dets:
        c.add(t_s, seq, label, track)
    v = c.view()
    assert v["start_s"] == start and v["interval_s"] == 600.0
    assert {x["label"]: (x["visits"], x["max_n"]) for x in v["labels"]} == expected


def test_counts_from_result_lines_skip_unconfirmed_tracks() -> None:
    st = ViewState(interval_s=60.0)
    t_ns = time.time_ns()
    dets = [messages.Detection(label="crab", confidence=0.9, box=(1, 2, 30, 40))] * 3
    for kind, fields in _det_lines(1, t_ns, dets, [3, 4, None]):
        st.on_result(kind, fields, t_ns / 1e9)
    counts = st.snapshot(0.0)["counts"]
    assert counts["labels"] == [{"label": "crab", "visits": 2, "max_n": 2}]
    assert counts["start_s"] == pytest.approx(t_ns / 1e9 // 60 * 60, abs=1)


def test_gated_now_follows_the_gated_counter() -> None:
    st = ViewState()
    for i, (gated, kept) in enumerate(((0, 5), (4, 5), (4, 0), (9, 5))):
        stats = messages.Stats(t_wall_ns=0, uptime_s=float(i), pairs_in=10 * i, rate_in=10.0,
                               malformed=0, pools={
                                   "mono": messages.PoolStats(gated=gated, kept=kept),
                                   "vo": messages.PoolStats(processed=10 * i)})
        st.on_stats(stats, now=float(i))
        pools = st.snapshot(float(i))["pools"]
        assert pools["mono"]["gated_now"] == (i in (1, 3)), i
        assert pools["vo"]["gated_now"] is False
