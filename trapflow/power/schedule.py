"""Recording windows, pure: given a schedule and a wall time (UTC epoch seconds), whether the
trap records now, when the current window ends and when the next one begins; and what to do
between two windows (wait up, or power off with a wake alarm).

A schedule is the intersection of its rules, each a union of half-open intervals
[start, end) on the time line: periodic windows, daily clock windows, and the day less a
margin around sunrise and sunset. The sun's times come from a function of the UTC date,
so the core stays pure and the tests need no ephemeris (`sun_events` makes one from the
`sun` extra). Wall time decides windows only; the shell turns what is left of one into a
monotonic deadline.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from trapflow.config.schedule import ScheduleConfig

DAY_S = 86400.0
HORIZON_S = 8 * DAY_S
"""How far ahead a window is looked for: a schedule with none in 8 days has none."""
FIRST_SPAN_S = 2 * 3600.0

Interval = tuple[float, float]
SunEvents = Callable[[dt.date], Sequence[float]]
"""The epoch seconds of a UTC date's sunrise and sunset (fewer in a polar day or night)."""


@dataclass(frozen=True)
class Schedule:
    """The rules, in seconds. A rule left out (None, empty) does not restrict."""

    every_s: float | None = None
    for_s: float = 0.0
    offset_s: float = 0.0
    clock: tuple[tuple[float, float], ...] = ()
    """Daily windows as (start, end) seconds of the UTC day; end <= start wraps."""
    sun_margin_s: float = 0.0
    sun: SunEvents | None = None


@dataclass(frozen=True)
class Verdict:
    """Where a wall time stands."""

    inside: bool
    ends_at: float | None
    """Inside: when this window ends (None: not within the horizon)."""
    next_start: float | None
    """When the next window begins (after this one, when inside; None: none in the horizon)."""


@dataclass(frozen=True)
class Idle:
    """Stay up (pipeline stopped) until `until` (epoch seconds; None: no next window)."""

    until: float | None


@dataclass(frozen=True)
class PowerOff:
    """Set the wake alarm at `wake_at` (epoch seconds), then power off."""

    wake_at: int
    next_start: float


def from_config(cfg: ScheduleConfig, sun: SunEvents | None = None) -> Schedule | None:
    """The config's schedule (None: no rule, always recording). The sun rule's events come
    from `sun`, else from the sun extra at the config's latitude and longitude."""
    if not cfg.enabled:
        return None
    if cfg.sun_margin_min > 0 and sun is None:
        assert cfg.latitude is not None and cfg.longitude is not None  # the config checks
        sun = sun_events(cfg.latitude, cfg.longitude)
    return Schedule(
        every_s=cfg.every_min * 60.0 if cfg.every_min > 0 else None,
        for_s=cfg.for_min * 60.0, offset_s=cfg.offset_min * 60.0,
        clock=tuple((a * 60.0, b * 60.0) for a, b in cfg.clock_windows()),
        sun_margin_s=cfg.sun_margin_min * 60.0, sun=sun if cfg.sun_margin_min > 0 else None)


def sun_events(latitude: float, longitude: float) -> SunEvents:
    """Sunrise and sunset of a UTC date at a place, from the sun extra (astral)."""
    from astral import Observer
    from astral import sun as astral_sun

    observer = Observer(latitude=latitude, longitude=longitude)

    def events(day: dt.date) -> list[float]:
        out = []
        for event in (astral_sun.sunrise, astral_sun.sunset):
            try:
                out.append(event(observer, day, tzinfo=dt.timezone.utc).timestamp())
            except ValueError:  # a polar day or night: the sun does not cross the horizon
                continue
        return out

    return events


def _periodic(s: Schedule, lo: float, hi: float) -> list[Interval]:
    assert s.every_s is not None
    k = math.floor((lo - s.offset_s - s.for_s) / s.every_s)
    out = []
    while (start := s.offset_s + k * s.every_s) < hi:
        out.append((start, start + s.for_s))
        k += 1
    return out


def _days(lo: float, hi: float) -> range:
    """UTC day numbers (since the epoch) touching [lo, hi), with one either side."""
    return range(math.floor(lo / DAY_S) - 1, math.floor(hi / DAY_S) + 2)


def _clock(s: Schedule, lo: float, hi: float) -> list[Interval]:
    out = []
    for day in _days(lo, hi):
        for a, b in s.clock:
            end = b if b > a else b + DAY_S
            out.append((day * DAY_S + a, day * DAY_S + end))
    return out


def _sun_skips(s: Schedule, lo: float, hi: float) -> list[Interval]:
    assert s.sun is not None
    out: list[Interval] = []
    for day in _days(lo, hi):
        date = dt.date(1970, 1, 1) + dt.timedelta(days=day)
        out.extend((t - s.sun_margin_s, t + s.sun_margin_s) for t in s.sun(date))
    return out


def _merged(intervals: list[Interval], lo: float, hi: float) -> list[Interval]:
    """Sorted, overlapping and touching ones joined, clipped to [lo, hi)."""
    out: list[Interval] = []
    for a, b in sorted(intervals):
        a, b = max(a, lo), min(b, hi)
        if a >= b:
            continue
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out


def _intersect(xs: list[Interval], ys: list[Interval]) -> list[Interval]:
    out, i, j = [], 0, 0
    while i < len(xs) and j < len(ys):
        a, b = max(xs[i][0], ys[j][0]), min(xs[i][1], ys[j][1])
        if a < b:
            out.append((a, b))
        if xs[i][1] < ys[j][1]:
            i += 1
        else:
            j += 1
    return out


def _subtract(xs: list[Interval], cuts: list[Interval]) -> list[Interval]:
    out = []
    for a, b in xs:
        for c, d in cuts:
            if d <= a or c >= b:
                continue
            if c > a:
                out.append((a, c))
            a = max(a, d)
            if a >= b:
                break
        if a < b:
            out.append((a, b))
    return out


def windows(s: Schedule, lo: float, hi: float) -> list[Interval]:
    """The recording windows within [lo, hi), sorted and disjoint (clipped at both ends)."""
    found = [(lo, hi)]
    if s.every_s is not None:
        found = _intersect(found, _merged(_periodic(s, lo, hi), lo, hi))
    if s.clock:
        found = _intersect(found, _merged(_clock(s, lo, hi), lo, hi))
    if s.sun is not None and s.sun_margin_s > 0:
        found = _subtract(found, _merged(_sun_skips(s, lo, hi), lo, hi))
    return found


def verdict(s: Schedule, t: float) -> Verdict:
    """Whether `t` is inside a window, when that window ends, when the next begins."""
    span = FIRST_SPAN_S
    while True:
        hi = t + span
        found = windows(s, t, hi)
        inside = bool(found) and found[0][0] <= t
        ends_at = found[0][1] if inside and found[0][1] < hi else None
        later = found[1:] if inside else found
        next_start = later[0][0] if later else None
        if (not inside or ends_at is not None) and next_start is not None:
            return Verdict(inside, ends_at, next_start)
        if span >= HORIZON_S:
            return Verdict(inside, ends_at, next_start)
        span = min(span * 4, HORIZON_S)


def between(v: Verdict, now: float, mode: str, boot_margin_s: float,
            min_off_s: float) -> Idle | PowerOff:
    """Outside a window at `now`: wait up, or power off to wake `boot_margin_s` before the
    next window, when mode is poweroff and the board would be off at least `min_off_s`."""
    if v.next_start is None:
        return Idle(None)
    wake_at = math.floor(v.next_start - boot_margin_s)
    if mode == "poweroff" and wake_at - now >= min_off_s:
        return PowerOff(wake_at, v.next_start)
    return Idle(v.next_start)


def per_day(s: Schedule | None, day: dt.date, days: int = 7) -> tuple[float, float]:
    """Windows begun and seconds recorded a day, the mean over `days` UTC days from `day`
    (no schedule: one window, the whole day)."""
    if s is None:
        return 1.0, DAY_S
    lo = (day - dt.date(1970, 1, 1)).days * DAY_S
    hi = lo + days * DAY_S
    found = windows(s, lo, hi)
    begun = sum(1 for a, _ in found if a > lo or not windows(s, lo - 1.0, lo))
    return begun / days, sum(b - a for a, b in found) / days


RECHECK_S = 3600.0
"""A window that does not end within the horizon is looked at again this often."""


@dataclass
class WindowClock:
    """The end of the window a run records in, as a deadline on the monotonic clock (a
    wall-clock step does not shorten or stretch it); at the deadline the wall time decides
    again, and a window that still holds (the clock stepped back, or it goes on) sets a new
    deadline. Pure: the caller passes both clocks' readings."""

    schedule: Schedule
    deadline: float | None
    """Monotonic seconds; None: no deadline (outside a window when started: due at once)."""

    @classmethod
    def start(cls, schedule: Schedule, mono: float, wall: float) -> WindowClock:
        clock = cls(schedule, None)
        clock.deadline = clock._deadline(verdict(schedule, wall), mono, wall)
        return clock

    @staticmethod
    def _deadline(v: Verdict, mono: float, wall: float) -> float | None:
        if not v.inside:
            return None
        return mono + (v.ends_at - wall if v.ends_at is not None else RECHECK_S)

    def due(self, mono: float, wall: float) -> bool:
        """Whether the window has ended (the run stops in order)."""
        if self.deadline is not None and mono < self.deadline:
            return False
        self.deadline = self._deadline(verdict(self.schedule, wall), mono, wall)
        return self.deadline is None
