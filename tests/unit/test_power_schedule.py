"""Recording windows: the schedule's rules decide, on a wall time, whether the trap records,
when the window ends and when the next begins; the config refuses what cannot work."""

from __future__ import annotations

import dataclasses
import datetime as dt
import importlib.util
from typing import Any

import pytest

from trapflow.config import schema as config
from trapflow.config.schedule import ScheduleConfig, parse_clock_window
from trapflow.errors import ConfigError
from trapflow.power.schedule import (
    Idle,
    PowerOff,
    Schedule,
    Verdict,
    between,
    from_config,
    per_day,
    verdict,
)

H = 3600.0
DAY = 24 * H
T0 = dt.datetime(2026, 12, 1, tzinfo=dt.timezone.utc).timestamp()  # a UTC midnight


def _at(hh: int, mm: int = 0, ss: float = 0.0, day: int = 0) -> float:
    return T0 + day * DAY + hh * H + mm * 60 + ss


def _schedule(**kw: Any) -> Schedule:
    s = from_config(ScheduleConfig(**kw))
    assert s is not None
    return s


HOURLY = {"every_min": 60, "for_min": 10}  # 10 minutes an hour, on the hour


@pytest.mark.parametrize(("rules", "t", "expected"), [
    # periodic: the start is inside, the end is not (half-open windows)
    (HOURLY, _at(5), Verdict(True, _at(5, 10), _at(6))),
    (HOURLY, _at(5, 9, 59.9), Verdict(True, _at(5, 10), _at(6))),
    (HOURLY, _at(5, 10), Verdict(False, None, _at(6))),
    (HOURLY, _at(23, 30), Verdict(False, None, _at(0, day=1))),  # over midnight
    ({**HOURLY, "offset_min": 15}, _at(5), Verdict(False, None, _at(5, 15))),
    ({**HOURLY, "offset_min": 15}, _at(5, 20), Verdict(True, _at(5, 25), _at(6, 15))),
    # seconds for tests: every 6 s for 3 s
    ({"every_min": 0.1, "for_min": 0.05}, _at(0, 0, 7), Verdict(True, _at(0, 0, 9),
                                                                 _at(0, 0, 12))),
    # clock windows, UTC; a window that wraps midnight
    ({"windows": ["06:00-18:00"]}, _at(5, 59), Verdict(False, None, _at(6))),
    ({"windows": ["06:00-18:00"]}, _at(12), Verdict(True, _at(18), _at(6, day=1))),
    ({"windows": ["22:00-02:00"]}, _at(23), Verdict(True, _at(2, day=1), _at(22, day=1))),
    ({"windows": ["22:00-02:00"]}, _at(1), Verdict(True, _at(2), _at(22))),
    ({"windows": ["22:00-02:00"]}, _at(2), Verdict(False, None, _at(22))),
    ({"windows": ["18:00-24:00"]}, _at(20), Verdict(True, _at(0, day=1), _at(18, day=1))),
    ({"windows": ["00:00-24:00"]}, _at(20), Verdict(True, None, None)),  # never ends
    # two windows a day, and windows that touch are one
    ({"windows": ["06:00-08:00", "16:00-18:00"]}, _at(9), Verdict(False, None, _at(16))),
    ({"windows": ["06:00-08:00", "08:00-09:00"]}, _at(7), Verdict(True, _at(9), _at(6, day=1))),
    # rules together: where all agree (hourly, only in the day)
    ({**HOURLY, "windows": ["06:00-18:00"]}, _at(18), Verdict(False, None, _at(6, day=1))),
    ({**HOURLY, "windows": ["06:05-18:00"]}, _at(6), Verdict(False, None, _at(6, 5))),
    ({**HOURLY, "windows": ["06:05-18:00"]}, _at(6, 5), Verdict(True, _at(6, 10), _at(7))),
    # rules that never agree: no window in the horizon
    ({**HOURLY, "windows": ["06:20-06:40"]}, _at(5), Verdict(False, None, None)),
])
def test_verdict(rules: dict[str, Any], t: float, expected: Verdict) -> None:
    assert verdict(_schedule(**rules), t) == expected


def _fixed_sun(day: dt.date) -> list[float]:
    """Sunrise 06:00 and sunset 18:00 UTC every day."""
    midnight = dt.datetime(day.year, day.month, day.day, tzinfo=dt.timezone.utc).timestamp()
    return [midnight + 6 * H, midnight + 18 * H]


@pytest.mark.parametrize(("rules", "t", "expected"), [
    ({}, _at(5), Verdict(True, _at(5, 30), _at(6, 30))),  # 30 min either side of sunrise
    ({}, _at(5, 30), Verdict(False, None, _at(6, 30))),
    ({}, _at(12), Verdict(True, _at(17, 30), _at(18, 30))),
    ({"windows": ["06:00-18:00"]}, _at(4), Verdict(False, None, _at(6, 30))),
    (HOURLY, _at(6), Verdict(False, None, _at(7))),  # the sunrise hour's window skipped
    (HOURLY, _at(17, 55), Verdict(False, None, _at(19))),
])
def test_sun_margins(rules: dict[str, Any], t: float, expected: Verdict) -> None:
    """30 minutes either side of a fixed sunrise and sunset (the sun's times are a function
    of the date: no ephemeris needed)."""
    base = from_config(ScheduleConfig(**rules)) or Schedule()
    s = dataclasses.replace(base, sun_margin_s=1800.0, sun=_fixed_sun)
    assert verdict(s, t) == expected


@pytest.mark.skipif(importlib.util.find_spec("astral") is None, reason="the sun extra")
def test_sun_from_the_extra() -> None:
    """Sydney in December: sunrise about 18:40 UTC, sunset about 08:55 UTC."""
    s = _schedule(sun_margin_min=30, latitude=-33.87, longitude=151.21)
    v = verdict(s, _at(12))  # night there: records until 30 minutes before sunrise
    assert v.inside and v.ends_at is not None and v.next_start is not None
    assert _at(18) < v.ends_at < _at(18, 30)
    assert v.next_start - v.ends_at == pytest.approx(3600.0)
    windows, seconds = per_day(s, dt.date(2026, 12, 1))
    assert windows == 2.0 and seconds == pytest.approx(22 * H, abs=60)


def test_sun_in_a_polar_day_skips_nothing() -> None:
    pytest.importorskip("astral")
    s = _schedule(sun_margin_min=30, latitude=78.2, longitude=15.6)  # Svalbard, June
    t = dt.datetime(2026, 6, 21, tzinfo=dt.timezone.utc).timestamp()
    assert verdict(s, t) == Verdict(True, None, None)


@pytest.mark.parametrize(("v", "mode", "expected"), [
    (Verdict(False, None, _at(6)), "idle", Idle(_at(6))),
    (Verdict(False, None, _at(6)), "poweroff", PowerOff(int(_at(5, 58, 30)), _at(6))),
    # too short a gap to be worth a boot: waited out
    (Verdict(False, None, _at(5, 5)), "poweroff", Idle(_at(5, 5))),
    (Verdict(False, None, None), "poweroff", Idle(None)),
])
def test_between_windows(v: Verdict, mode: str, expected: Idle | PowerOff) -> None:
    assert between(v, _at(5), mode, boot_margin_s=90.0, min_off_s=300.0) == expected


def test_per_day() -> None:
    assert per_day(_schedule(**HOURLY), dt.date(2026, 12, 1)) == (24.0, 4 * H)
    assert per_day(_schedule(windows=["22:00-02:00"]), dt.date(2026, 12, 1)) == (1.0, 4 * H)
    assert per_day(None, dt.date(2026, 12, 1)) == (1.0, DAY)


def test_no_schedule_by_default() -> None:
    assert from_config(config.Config().schedule) is None


@pytest.mark.parametrize(("text", "minutes"), [
    ("06:00-18:30", (360, 1110)), ("22:00-02:00", (1320, 120)), ("0:00-24:00", (0, 1440)),
])
def test_clock_window_parses(text: str, minutes: tuple[int, int]) -> None:
    assert parse_clock_window(text) == minutes


@pytest.mark.parametrize(("data", "error"), [
    ({"schedule": {"every_min": 60, "for_min": 70}}, r"0 < for_min <= every_min.*\$.schedule"),
    ({"schedule": {"every_min": 60}}, "for_min"),
    ({"schedule": {"for_min": 10}}, "need every_min > 0"),
    ({"schedule": {"every_min": 60, "for_min": 10, "offset_min": 60}}, "offset_min <"),
    ({"schedule": {"windows": ["25:00-01:00"]}}, "HH:MM-HH:MM"),
    ({"schedule": {"windows": ["6-18"]}}, "HH:MM-HH:MM"),
    ({"schedule": {"windows": ["06:00-06:00"]}}, "no length"),
    ({"schedule": {"windows": ["24:00-02:00"]}}, "cannot start at 24:00"),
    ({"schedule": {"sun_margin_min": 30}}, "needs latitude and longitude"),
    ({"schedule": {"between": "sleep"}}, r"\$.schedule.between"),
    ({"schedule": {"between": "poweroff"}, "power": {"wake": "none"}}, "would not wake"),
    ({"power": {"wake": "command", "wake_command": "set-wake {when}"}}, r"\{epoch\}"),
    ({"power": {"wake": "command"}}, r"\{epoch\}"),
    ({"power": {"poweroff_command": " "}}, "poweroff_command is empty"),
])
def test_bad_schedules(data: dict[str, Any], error: str) -> None:
    with pytest.raises(ConfigError, match=error):
        config.from_data(data)


def test_the_sun_rule_without_the_extra_names_it(monkeypatch: pytest.MonkeyPatch) -> None:
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "astral" else real(name, *a))
    with pytest.raises(ConfigError, match=r"install the 'sun' extra.*trapflow\[sun\]"):
        config.from_data({"schedule": {"sun_margin_min": 30, "latitude": 1, "longitude": 2}})
