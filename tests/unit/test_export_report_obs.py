"""The run report's observation sections, pure: visits and MaxN per label per hour from
counts.jsonl, length-frequency histograms from tracks.jsonl (trapflow.export.report)."""

from __future__ import annotations

import pytest

from trapflow.export.report import RunSummary, histogram, observations, render_html, svg_bars

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
    tracks = [{"label": "crab", "length_m": 0.23}, {"label": "crab"},
              {"label": "fish", "length_m": 1.2}, {"label": "fish", "length_m": "x"}]
    observations(s, counts, tracks)
    assert s.counts_hour == {"2026-11-25 15:00": {"crab": [3, 3, 15.5], "fish": [1, 1, 3.0]},
                             "2026-11-25 16:00": {}}
    assert s.lengths == {"crab": [0.23], "fish": [1.2]}
    page = render_html(s)
    assert "<td>2026-11-25 15:00</td><td>crab</td><td>3</td><td>3</td><td>15.5</td>" in page
    assert page.count('class="bar"') == 2


def test_bars_carry_their_bin_and_count() -> None:
    svg = svg_bars("crab", [0.23, 0.231, 0.259])
    assert 'data-from="0.230" data-to="0.240" data-count="2"' in svg
    assert 'data-from="0.250" data-to="0.260" data-count="1"' in svg


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
