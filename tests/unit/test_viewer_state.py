"""The viewer's pure core and its metrics, with no sockets: addresses, result lines, the
pair it shows, chart points, and a /metrics exposition Prometheus's own parser reads."""

from __future__ import annotations

import re
import time
from pathlib import Path

import pytest
from prometheus_client.parser import text_string_to_metric_families

from trapflow import viewer
from trapflow.cli.view_params import parse_view
from trapflow.errors import ProtocolError
from trapflow.normalizer.result_json import dumps, normalize
from trapflow.viewer import metrics
from trapflow.viewer.state import Histogram, ViewState, parse_timestamp
from trapflow.wire import messages
from trapflow.wire.pool_counters import IN_PROGRESS, POOL_COUNTERS, UNFINISHED


@pytest.mark.parametrize(("text", "expected", "error"), [
    ("8090", ("127.0.0.1", 8090), None),
    ("0.0.0.0:80", ("0.0.0.0", 80), None),
    ("[::1]:9000", ("::1", 9000), None),
    ("localhost:65535", ("localhost", 65535), None),
    ("", None, "PORT in 1..65535"),
    ("0", None, "PORT in 1..65535"),
    ("65536", None, "PORT in 1..65535"),
    ("host:", None, "PORT in 1..65535"),
    (":8090", None, "host before ':'"),
    ("http://x:1", None, "host name or address"),
    ("::1:80", None, "host name or address"),
    ("8090x", None, "PORT in 1..65535"),
])
def test_view_address(text: str, expected: tuple[str, int] | None, error: str | None) -> None:
    if error is None:
        assert parse_view(text) == expected
    else:
        with pytest.raises(ValueError, match=error):
            parse_view(text)


@pytest.mark.parametrize(("data", "error"), [
    (b"", "result line"),
    (b"[1, 2]", "result line"),
    (b'{"a": 1}', "result line"),
    (b"{}", "expected one key"),
    (b'{"a": {}, "b": {}}', "expected one key"),
    (b"x" * (messages.MAX_RESULT_BYTES + 1), "expected at most"),
])
def test_result_line_rejected(data: bytes, error: str) -> None:
    with pytest.raises(ProtocolError, match=error):
        messages.decode_result_line(data)


def _line(body: messages.Body, seq: int, t_wall_ns: int) -> list[tuple[str, dict]]:
    res = messages.Result(seq=seq, t_wall_ns=t_wall_ns, t_mono_ns=0, pool="p", worker="w",
                          proc_ns=1, body=body)
    return [messages.decode_result_line(dumps(obj)) for obj in normalize(res)]


def _pair(seq: int) -> messages.StereoPair:
    return messages.StereoPair(seq=seq, t_wall_ns=0, t_mono_ns=0, t_left_ns=0, t_right_ns=0,
                               skew_ns=0, encoding="jpeg", width=64, height=48)


def test_shows_the_newest_pair_a_detector_answered_with_its_boxes_and_tags() -> None:
    st = ViewState(frame_hz=2.0)
    now_ns = time.time_ns()
    for seq in range(10):
        st.on_image(_pair(seq), b"L%d" % seq, b"R%d" % seq)
    det = messages.MonoIR(detections=[messages.Detection(label="crab", confidence=0.9,
                                                         box=(1, 2, 30, 40))])
    tag = messages.Tags(tags=[messages.Tag(id=7, corners=[(1, 1), (9, 1), (9, 9), (1, 9)])])
    for kind, fields in _line(det, 6, now_ns - 50_000_000) + _line(tag, 6, now_ns):
        st.on_result(kind, fields, now_ns / 1e9)
    assert st.tick(100.0)
    assert st.shown is not None and st.shown.seq == 6 and st.shown.left == b"L6"
    frame = st.snapshot(100.0)["frame"]
    assert frame["detections"] == [{"label": "crab", "confidence": 0.9, "box": [1, 2, 30, 40]}]
    assert frame["tags"][0]["id"] == 7 and len(frame["tags"][0]["corners"]) == 4
    # frame_hz: no other pick before half a second has passed, even with newer answers.
    for kind, fields in _line(det, 9, now_ns):
        st.on_result(kind, fields, now_ns / 1e9)
    assert not st.tick(100.4)
    assert st.tick(100.5) and st.shown.seq == 9
    assert st.latency["mono_ir"].n == 2 and 0.04 < st.latency["mono_ir"].total < 1.0


def test_no_answer_yet_shows_the_newest_pair() -> None:
    st = ViewState()
    for seq in (3, 4, 5):
        st.on_image(_pair(seq), b"l", b"r")
    assert st.tick(1.0) and st.shown is not None and st.shown.seq == 5
    assert st.snapshot(1.0)["frame"]["detections"] == []


def test_vo_top_view_and_ok_rate() -> None:
    st = ViewState()
    t = time.time_ns()
    for i, ok in enumerate((True, True, False, True)):
        pose = (1, 0, 0, 0.1 * i, 0, 1, 0, 0, 0, 0, 1, 0.5 * i)
        body = messages.StereoVO(ok=ok, rotation=(1, 0, 0, 0, 1, 0, 0, 0, 1), pose=pose)
        for kind, fields in _line(body, i, t):
            st.on_result(kind, fields, t / 1e9)
    vo = st.snapshot(0)["vo"]
    assert vo["ok_rate"] == 0.75 and vo["total"] == 4
    assert vo["path"] == [[0.0, 0.0], [0.1, 0.5], [0.2, 1.0], [0.3, 1.5]]


def test_chart_points_per_stats_message() -> None:
    st = ViewState()
    for i, dropped in enumerate((0, 4, 10)):
        stats = messages.Stats(t_wall_ns=0, uptime_s=float(i), pairs_in=10 * i, rate_in=10.0,
                               malformed=0, pools={"mono": messages.PoolStats(
                                   workers=2, dropped=dropped, rate=5.0 + i)})
        st.on_stats(stats, now=float(i))
    p = st.snapshot(3.0)["pools"]["mono"]
    assert p["rate"] == [5.0, 6.0, 7.0] and p["workers"] == [2, 2, 2]
    assert p["drops"] == [0.0, 4.0, 6.0]  # per second between stats messages


@pytest.mark.parametrize(("text", "ok"), [
    ("2025-07-07 12:52:43.120", True), ("2025-07-07 12:52:43", True),
    ("12:52:43", False), ("", False),
])
def test_timestamp(text: str, ok: bool) -> None:
    if ok:
        assert parse_timestamp(text) == pytest.approx(1751892763.12 if "." in text
                                                      else 1751892763.0)
    else:
        with pytest.raises(ValueError, match="expected 'YYYY-MM-DD"):
            parse_timestamp(text)


def test_histogram_is_cumulative() -> None:
    h = Histogram(bounds=(0.1, 1.0), counts=[0, 0, 0])
    for v in (0.05, 0.5, 0.7, 3.0):
        h.observe(v)
    assert h.cumulative() == [("0.1", 1), ("1.0", 3), ("+Inf", 4)]


def test_exposition_parses_and_follows_naming(tmp_path: Path) -> None:
    st = ViewState()
    st.on_stats(messages.Stats(t_wall_ns=0, uptime_s=3.0, pairs_in=30, rate_in=10.0,
                               malformed=1, pools={"mono": messages.PoolStats(
                                   workers=1, received=30, processed=25, dropped=4, lost=1)}),
                now=1.0)
    st.on_status({"nodes": [
        {"name": "worker:mono:0", "state": "active", "restarts": 2, "reason": "",
         "counters": {"processed": 25, "proc_us": 500_000}},
        {"name": "modem", "state": "inactive", "restarts": 0, "reason": "no port",
         "counters": {"backlog": 12}}],
        "ring": {"slots": 12, "free": 9, "held": 3}})
    t = time.time_ns()
    for kind, fields in _line(messages.StereoIR(label="crab", confidence=0.5), 3, t):
        st.on_result(kind, fields, t / 1e9 + 0.2)
    snap = st.snapshot(1.0)
    assert snap["modem"] == {"state": "inactive", "reason": "no port", "backlog": 12,
                             "in_flight": 0, "bytes_last_hour": 0}
    assert [n["name"] for n in snap["nodes"]] == ["worker:mono:0", "modem"]
    reg = metrics.registry_for(st, tmp_path)
    fams = {f.name: f for f in text_string_to_metric_families(
        metrics.exposition(reg).decode())}

    def value(name: str, **labels: str) -> float:
        fam_name = name.removesuffix("_total").removesuffix("_count").removesuffix("_sum")
        fam_name = fam_name.removesuffix("_bucket")
        return next(s.value for s in fams[fam_name].samples
                    if s.name == name and all(s.labels.get(k) == v for k, v in labels.items()))

    assert value("trapflow_pool_processed_pairs_total", pool="mono") == 25
    assert value("trapflow_pool_dropped_pairs_total", pool="mono") == 4
    assert value("trapflow_pool_lost_pairs_total", pool="mono") == 1
    assert value("trapflow_pairs_received_total") == 30
    assert value("trapflow_node_restarts_total", node="worker:mono:0") == 2
    assert value("trapflow_node_state", node="modem", state="inactive") == 1
    assert value("trapflow_node_state", node="modem", state="active") == 0
    assert value("trapflow_outbox_backlog_messages") == 12
    assert value("trapflow_ring_slots", state="held") == 3
    assert value("trapflow_pool_processing_seconds_sum", pool="mono") == pytest.approx(0.5)
    assert value("trapflow_pool_processing_seconds_count", pool="mono") == 25
    assert value("trapflow_result_latency_seconds_bucket", algorithm="stereo_ir",
                 le="0.25") == 1
    assert value("trapflow_result_latency_seconds_bucket", algorithm="stereo_ir",
                 le="0.1") == 0
    for fam in fams.values():
        assert fam.name.startswith("trapflow_"), fam.name
        if fam.type == "counter":
            assert all(s.name.endswith(("_total", "_created")) for s in fam.samples), fam.name
    out = tmp_path / "textfile" / "trapflow.prom"
    metrics.write_textfile(reg, out)
    again = {f.name for f in text_string_to_metric_families(out.read_text())}
    assert again == set(fams)
    assert not list(out.parent.glob("*.tmp*"))  # written to a temporary name, then renamed


@pytest.mark.parametrize(("rel", "served"), [
    ("ev1/left/00000001.jpg", True),
    ("ev1/left/../left/00000001.jpg", True),
    ("ev1/event.json", False),
    ("../secret.jpg", False),
    ("ev1/../../secret.jpg", False),
    ("/etc/secret.jpg", False),
    ("ev1/left/missing.jpg", False),
])
def test_event_images_only_from_the_events_folder(tmp_path: Path, rel: str, served: bool) -> None:
    from trapflow.config.schema import Config
    from trapflow.viewer.taps import PipelineTaps

    run = tmp_path / "run"
    (run / "events" / "ev1" / "left").mkdir(parents=True)
    (run / "events" / "ev1" / "left" / "00000001.jpg").write_bytes(b"\xff\xd8")
    (run / "events" / "ev1" / "event.json").write_text("{}")
    (run / "secret.jpg").write_bytes(b"no")
    taps = PipelineTaps(Config(), run, ViewState())
    try:
        path = taps.event_file(rel)
        assert (path is not None) == served
        if served:
            assert path == (run / "events" / "ev1" / "left" / "00000001.jpg").resolve()
        taps.scan_events()
        assert taps.state.events == [{"name": "ev1", "pairs": None, "open": True,
                                      "thumb": "ev1/left/00000001.jpg"}]
    finally:
        taps.close()


def _status(**extra: object) -> dict[str, object]:
    return {"nodes": [], "ledger": None, **extra, "supervision": {
        "pools": {"mono": {"state": "inactive", "count": 2, "policy": "latest", "params": {},
                           "changes": 2},
                  "vo": {"state": "active", "count": 1, "policy": "fifo:4", "params": {},
                         "changes": 0}},
        "timeline": [{"t_s": 3.0, "node": "pool:mono", "kind": "control",
                      "reason": "count 1 -> 2"},
                     {"t_s": 4.0, "node": "worker:vo:0", "kind": "retry", "reason": "x"},
                     {"t_s": 5.5, "node": "pool:mono", "kind": "control",
                      "reason": "deactivated (was active)"}]}}


def test_pool_control_state_with_its_last_change() -> None:
    v = ViewState()
    v.on_status(_status())
    snap = v.snapshot(0.0)
    assert snap["control"]["mono"]["state"] == "inactive"
    assert snap["control"]["mono"]["count"] == 2
    assert snap["control"]["mono"]["last_change"] == {"t_s": 5.5,
                                                      "change": "deactivated (was active)"}
    assert snap["control"]["vo"]["last_change"] is None
    # No ladder in this status: the page hides the level.
    assert snap["level"] is None and snap["level_reason"] is None


def test_ladder_level_from_the_supervision_status() -> None:
    v = ViewState()
    st = _status()
    st["supervision"]["ladder"] = {  # type: ignore[index]
        "level": "mono_vo", "index": 2, "levels": ["full", "ir_slowed", "mono_vo"],
        "reason": "cpu_temp_c 86 C >= 85 C for 30 s", "forced": False, "changes": 2}
    v.on_status(st)
    snap = v.snapshot(0.0)
    assert (snap["level"], snap["level_reason"], snap["level_forced"]) == \
        ("mono_vo", "cpu_temp_c 86 C >= 85 C for 30 s", False)


def test_ladder_level_as_top_level_fields() -> None:
    v = ViewState()
    v.on_status(_status(level="mono_vo", level_reason="cpu 82 C > 80 C"))
    snap = v.snapshot(0.0)
    assert (snap["level"], snap["level_reason"]) == ("mono_vo", "cpu 82 C > 80 C")


def test_no_status_yet_has_no_control() -> None:
    assert ViewState().snapshot(0.0)["control"] == {}


def test_energy_gauges_from_the_status_ledger(tmp_path: Path) -> None:
    """/metrics serves the run's energy estimate as ledger.json has it: a Pi 5 (2.7 W idle,
    1.3 W per busy core, 0.2 W per camera) with 54 CPU seconds in an hour is 2.7 +
    1.3 x 0.015 + 0.4 = 3.12 W, 74.9 Wh a day, 100 Wh x 0.8 usable lasts 1.1 days."""
    from trapflow.config.schema import EnergyConfig
    from trapflow.supervisor.report import energy_section, energy_text

    energy = energy_section(EnergyConfig(battery_wh=100.0), {"capture": 36.0, "mono": 18.0},
                            3600.0, (600, 3000))
    st = ViewState()
    st.on_status({"nodes": [], "ledger": {"energy": energy}})
    fams = {f.name: f for f in text_string_to_metric_families(
        metrics.exposition(metrics.registry_for(st, tmp_path)).decode())}

    def value(name: str, **labels: str) -> float:
        return next(s.value for s in fams[name].samples
                    if all(s.labels.get(k) == v for k, v in labels.items()))

    assert value("trapflow_energy_watts") == 3.12
    assert value("trapflow_energy_watt_hours_per_day") == 74.9
    assert value("trapflow_energy_battery_days") == 1.1
    assert value("trapflow_energy_cpu_seconds_per_hour", role="mono") == 18.0
    assert value("trapflow_gate_active_seconds") == 600
    assert value("trapflow_gate_idle_seconds") == 3000
    assert energy_text(energy) == (
        "energy (pi5 model): 0.015 cores busy, 3.12 W, 74.9 Wh/day, 1.1 days on the battery; "
        "motion gate active 600 s (17 %), idle 3000 s\n")


def test_no_energy_yet_gives_empty_gauges(tmp_path: Path) -> None:
    fams = {f.name: f for f in text_string_to_metric_families(
        metrics.exposition(metrics.registry_for(ViewState(), tmp_path)).decode())}
    assert fams["trapflow_energy_watts"].samples == []


def test_the_state_carries_every_ledger_state_and_the_page_names_none() -> None:
    """Regression: the page listed a pool's ledger states by hand and left out gated,
    dropped_stale and dropped_by_level. The state JSON now carries the list of states with
    their labels (wire.pool_counters.LEDGER_STATES, derived from POOL_COUNTERS), and the
    page iterates it."""
    v = ViewState()
    v.on_status(_status(ledger={"pools": {"mono": {"processed": 3, "gated": 9}}}))
    snap = v.snapshot(0.0)
    keys = [s["key"] for s in snap["ledger_states"]]
    assert set(keys) == {c.ledger for c in POOL_COUNTERS if c.ledger} | {UNFINISHED, IN_PROGRESS}
    assert "gated" in keys and len(set(keys)) == len(keys)
    assert all(s["label"] for s in snap["ledger_states"])
    js = (Path(viewer.__file__).parent / "static" / "viewer.js").read_text()
    named = {c.ledger for c in POOL_COUNTERS if c.ledger} - {"processed", "lost"}  # always shown
    assert not [k for k in named if re.search(rf"\bp\.{k}\b|[\"']{k}[\"']", js)]
