"""What a schedule costs: the day split into recording, booting, idle and off, and the Wh a
day from the same board model as ledger.json's energy line."""

from __future__ import annotations

import datetime as dt

import pytest

from trapflow.power.energy import BOARDS, RECORDING_CPU_S_PER_HOUR, estimate
from trapflow.power.plan import DaySplit, airtime_s, plan, split_day
from trapflow.power.schedule import Schedule

PI5 = BOARDS["pi5"]
DAY = dt.date(2026, 12, 1)
HOURLY = Schedule(every_s=3600.0, for_s=600.0)  # 10 minutes an hour


@pytest.mark.parametrize(("s", "mode", "expected"), [
    (None, "idle", DaySplit(1.0, 86400.0)),
    (HOURLY, "idle", DaySplit(24.0, 4 * 3600.0, idle_s=20 * 3600.0)),
    (HOURLY, "poweroff", DaySplit(24.0, 4 * 3600.0, booting_s=24 * 90.0,
                                  off_s=20 * 3600.0 - 24 * 90.0)),
    # gaps too short to power off are waited up: every 6 min for 3
    (Schedule(every_s=360.0, for_s=180.0), "poweroff", DaySplit(240.0, 12 * 3600.0,
                                                               idle_s=12 * 3600.0)),
    # one window a day, 06:00-18:00
    (Schedule(clock=((6 * 3600.0, 18 * 3600.0),)), "poweroff",
     DaySplit(1.0, 12 * 3600.0, booting_s=90.0, off_s=12 * 3600.0 - 90.0)),
])
def test_split_day(s: Schedule | None, mode: str, expected: DaySplit) -> None:
    assert split_day(s, DAY, 7, mode, boot_margin_s=90.0, min_off_s=300.0) == expected


def test_no_schedule_costs_what_the_ledger_says() -> None:
    """Always recording: the plan's Wh a day is ledger.json's energy line for the same CPU."""
    p = plan(PI5, split_day(None, DAY, 7, "idle", 90.0, 300.0), RECORDING_CPU_S_PER_HOUR)
    ledger = estimate(PI5, RECORDING_CPU_S_PER_HOUR, 3600.0, cameras=2)
    assert p.wh_per_day == pytest.approx(ledger.wh_per_day)
    assert p.days is None


def test_ten_minutes_an_hour_powered_off_lasts_a_month() -> None:
    """The documented example: a Pi 5 on 1,000 Wh (80 % usable), 10 minutes an hour."""
    split = split_day(HOURLY, DAY, 7, "poweroff", 90.0, 300.0)
    p = plan(PI5, split, RECORDING_CPU_S_PER_HOUR, battery_wh=1000.0, usable=0.8)
    recording_w = 2.7 + 0.4 + 1.3 * 898.0 / 3600.0
    assert p.recording_w == pytest.approx(recording_w)
    assert p.wh_per_day == pytest.approx(4 * recording_w + 0.6 * 4.0 + 19.4 * 0.01)
    assert p.days is not None and p.days >= 30
    idle = plan(PI5, split_day(HOURLY, DAY, 7, "idle", 90.0, 300.0), RECORDING_CPU_S_PER_HOUR,
                battery_wh=1000.0, usable=0.8)
    assert idle.days is not None and idle.days < 15  # staying up costs most of it


def test_airtime() -> None:
    """1,080 bytes a recording hour, 4 hours a day at 300 bit/s: 144 s a day."""
    assert airtime_s(1080.0, DaySplit(24.0, 4 * 3600.0), 300.0) == pytest.approx(144.0)
