"""The run report's observation sections, pure: visits and MaxN per label per hour from
counts.jsonl, length-frequency histograms from tracks.jsonl (trapflow.export.report)."""

from __future__ import annotations

import re

import pytest

from tests.integration.test_export_report import Page
from trapflow.export.report import (
    PAD,
    PLOT_BOTTOM,
    RunSummary,
    W,
    histogram,
    observations,
    rate_bins,
    render_html,
    svg_bars,
    svg_lines,
)
from trapflow.wire.pool_counters import LEDGER_STATES

HOUR = 1795618800.0  # 2026-11-25 15:00 UTC


@pytest.mark.parametrize(("values", "width", "first", "counts"), [
    # narrowest width with at most 15 bins; bins aligned to multiples of it
    ([0.23, 0.259], 0.01, 23, [1, 0, 1]),
    # 0.3 / 0.05 is 5.999999999999999 in floats: still the bin from 0.30
    ([0.3, 1.0], 0.05, 6, [1] + [0] * 13 + [1]),
    ([0.3, 0.44], 0.01, 30, [1] + [0] * 13 + [1]),  # 15 bins: the most
    ([0.3, 0.46], 0.02, 15, [1, 0, 0, 0, 0, 0, 0, 0, 1]),
    ([0.5, 2.5], 0.2, 2, [1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1]),
    # one value: one bin
    ([1.0], 0.01, 100, [1]),
])
def test_histogram_bins(values: list[float], width: float, first: int,
                        counts: list[int]) -> None:
    assert histogram(values) == (width, first, counts)


def test_visits_and_max_n_per_hour() -> None:
    """An hour sums its intervals' visits and dwell and keeps the largest MaxN."""
    s = RunSummary(run="r")
    counts = [
        {"start_s": HOUR, "end_s": HOUR + 600, "pairs": 9, "labels": [
            {"label": "crab", "visits": 2, "max_n": 2, "dwell_s": 10.0},
            {"label": "fish", "visits": 1, "max_n": 1, "dwell_s": 3.0}]},
        {"start_s": HOUR + 600, "end_s": HOUR + 1200, "pairs": 9, "labels": [
            {"label": "crab", "visits": 1, "max_n": 3, "dwell_s": 5.5}]},
        {"start_s": HOUR + 3600, "end_s": HOUR + 4200, "pairs": 9, "labels": []},
        {"bogus": 1},  # skipped
    ]
    tracks = [{"label": "crab", "length_m": 0.23, "range_m": 1.52, "speed_m_s": 0.071},
              {"label": "crab", "range_m": 2.1},
              {"label": "fish", "length_m": 1.2}, {"label": "fish", "length_m": "x"}]
    observations(s, counts, tracks)
    assert s.counts_hour == {"2026-11-25 15:00": {"crab": [3, 3, 15.5], "fish": [1, 1, 3.0]},
                             "2026-11-25 16:00": {}}
    assert s.lengths == {"crab": [0.23], "fish": [1.2]}
    assert s.ranges == {"crab": [1.52, 2.1]} and s.speeds == {"crab": [0.071]}
    page = render_html(s)
    # label, tracks measured, median, min, max length, median range, median speed
    assert ("<td>crab</td><td>1</td><td>0.230</td><td>0.230</td><td>0.230</td><td>1.81</td>"
            "<td>0.071</td>") in page
    assert "<td>fish</td><td>1</td><td>1.200</td><td>1.200</td><td>1.200</td><td>-</td>" in page
    assert "<td>2026-11-25 15:00</td><td>crab</td><td>3</td><td>3</td><td>15.5</td>" in page
    assert page.count('class="bar"') == 2


def test_bars_carry_their_bin_and_count() -> None:
    svg = svg_bars("crab", [0.23, 0.231, 0.259])
    assert 'data-from="0.230" data-to="0.240" data-count="2"' in svg
    assert 'data-from="0.250" data-to="0.260" data-count="1"' in svg


@pytest.mark.parametrize(("times", "end", "want"), [
    # 5 pairs/s for 25 s: the last bin covers 5 s and holds 25 pairs, 5/s, not 2.5/s
    ([i / 5 for i in range(125)], 24.8, [(0, 5.0), (10, 5.0), (20, 25 / 4.8)]),
    # the run ends 1 s into its last bin: too short for a rate, left out
    ([i / 5 for i in range(55)], 10.8, [(0, 5.0)]),
    # a run shorter than one bin keeps its only bin, over the time it covers
    ([i / 5 for i in range(20)], 3.8, [(0, 20 / 3.8)]),
    # a pool that stopped early shows zeros up to the run's end, not a shorter line
    ([0.0, 1.0], 24.8, [(0, 0.2), (10, 0.0), (20, 0.0)]),
    ([], 10.0, []),
])
def test_rate_bins_last_bin_by_the_time_it_covers(times: list[float], end: float,
                                                  want: list[tuple[float, float]]) -> None:
    """Regression (issue 22, item 11): the rate lines dived in the last bin, which the run's
    end cut short, as its count was divided by the whole bin width."""
    got = rate_bins(times, end)
    assert [t for t, _ in got] == [t for t, _ in want]
    assert [r for _, r in got] == pytest.approx([r for _, r in want])


def _pixels(svg: str) -> list[tuple[float, float]]:
    """The points of the one polyline of a chart, in pixels."""
    m = re.search(r' points="([^"]+)"', svg)
    assert m, svg
    return [(float(p.split(",")[0]), float(p.split(",")[1])) for p in m.group(1).split()]


@pytest.mark.parametrize("path", [
    [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)],        # as wide as deep
    [(0.0, 0.0), (0.2, 0.0), (0.0, 3.0)],        # a dive straight ahead
    [(0.0, 0.0), (3.0, 0.0), (0.0, 0.1)],        # a transect sideways
])
def test_vo_path_has_equal_axes(path: list[tuple[float, float]]) -> None:
    """Regression (issue 22, item 11): the VO path was squashed about 3.5:1 (equal data
    ranges on a frame 3.5 times wider than high). A metre is as many pixels both ways."""
    svg = svg_lines("VO path from above", {"left camera": path}, "x (m)", "z (m)", equal=True)
    px = _pixels(svg)
    x_per_m = (px[1][0] - px[0][0]) / (path[1][0] - path[0][0])
    y_per_m = (px[0][1] - px[2][1]) / (path[2][1] - path[0][1])  # up the page is +z
    assert x_per_m == pytest.approx(y_per_m, rel=2e-2)  # pixels are written to 0.1
    xs, ys = [p[0] for p in px], [p[1] for p in px]  # and the path stays inside the frame
    assert min(xs) >= PAD - 0.1 and max(xs) <= W - PAD + 0.1
    assert min(ys) >= PAD // 2 - 0.1 and max(ys) <= PLOT_BOTTOM + 0.1


def test_run_metadata_section() -> None:
    """Regression (issue 22, item 11): the report had no config, versions, rig or duration."""
    s = RunSummary(run="r", meta={
        "started": "2026-11-25 15:00:00", "ended": "2026-11-25 15:00:20", "duration_s": 20.3,
        "config": {"digest": "0123456789ab", "source": {"kind": "synthetic", "uri": "",
                   "size": "320x240", "rate_hz": 5.0},
                   "pools": {"mono": {"count": 1, "policy": "latest", "plugin": "mono"}}},
        "rig": {"calib": "3f9c2a1b", "origin": "the synthetic world",
                "describe": "320x240, baseline 0.120 m (calib 3f9c2a1b)"},
        "versions": {"python": "3.11.7", "trapflow": "0.9.0", "onnxruntime": ""}})
    page = render_html(s)
    for text in ("20.3 s", "digest 0123456789ab", "mono x1 mono (latest)", "calib 3f9c2a1b",
                 "trapflow 0.9.0", "python 3.11.7"):
        assert text in page, text
    assert "onnxruntime" not in page  # not installed: not claimed
    assert "no run.json" in render_html(RunSummary(run="old"))


def test_energy_section_with_active_and_idle_time() -> None:
    """The report shows the power model's estimate and the motion gate's active vs idle
    time from ledger.json's `energy`; a run without a ledger says so."""
    s = RunSummary(run="r", ledger={"energy": {
        "board": "pi5", "watts": 3.65, "wh_per_day": 87.6, "busy_cores": 0.42,
        "days_on_battery": 4.6, "active_s": 40, "idle_s": 290,
        "cpu_s_per_hour": {"mono": 300.0, "capture": 900.0}}})
    page = render_html(s)
    energy = page.split("<h2>Energy</h2>")[1].split("<h2>")[0]
    for cell in ("<td>3.65</td>", "<td>87.6</td>", "<td>4.6</td>", "<td>40 (12 %)</td>",
                 "<td>290</td>", "<td>mono</td><td>300.0</td>"):
        assert cell in energy, (cell, energy)
    bare = render_html(RunSummary(run="r")).split("<h2>Energy</h2>")[1]
    assert bare.startswith("\n<p>no energy estimate")


def test_every_ledger_state_of_every_pool_is_on_the_page() -> None:
    """Regression: the report's table of drops and losses named its columns by hand and
    left out gated, dropped_stale, dropped_inactive and dropped_by_level; a motion-gated
    pool's withheld pairs were missing from the page. Now the columns come from the
    ledger's state list (wire.pool_counters.LEDGER_STATES): every state a pool holds pairs
    in shows with its number."""
    states = [key for key, _label in LEDGER_STATES]
    # Pool `all` holds a distinct number in every state; `some` only in a few.
    pools = {"all": {key: 10 + i for i, key in enumerate(states)},
             "some": {"processed": 5, "gated": 7, "lost": 0, "policy": "latest"}}
    page = Page()  # the report test's own reading of the page
    page.feed(render_html(RunSummary(run="r", ledger={"pools": pools})))
    head, *rows = next(t for t in page.tables if t[0][:2] == ["pool", "processed"])
    label = dict(LEDGER_STATES)
    assert head[1:] == [label[key] for key in states]
    got = {r[0]: dict(zip(head[1:], r[1:], strict=True)) for r in rows}
    assert got["all"] == {label[key]: str(10 + i) for i, key in enumerate(states)}
    assert got["some"]["gated"] == "7" and got["some"]["processed"] == "5"
    assert got["some"]["dropped stale"] == "0"
    # A state no pool reached is no column; processed and lost always are.
    page = Page()  # the report test's own reading of the page
    page.feed(render_html(RunSummary(run="r", ledger={"pools": {"some": pools["some"]}})))
    head, *rows = next(t for t in page.tables if t[0][:2] == ["pool", "processed"])
    assert head == ["pool", "processed", "gated", "lost"]
    assert rows == [["some", "5", "7", "0"]]
