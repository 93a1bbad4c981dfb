"""Deployment schedules and the wake mechanism: when the trap records, and how the board
sleeps and wakes between recording windows (docs/gate-and-energy.md, "Schedules").

The windows' grammar ("HH:MM-HH:MM", UTC) is parsed here and only here (`clock_windows`);
the decisions on a wall time are trapflow.power.schedule's.
"""

from __future__ import annotations

import importlib.util
import string
from typing import Annotated, Literal

import msgspec

from trapflow.config.base import Section

MINUTES_PER_DAY = 24 * 60
SUN_EXTRA = "sun"
"""The optional extra that brings the sun's position (the astral package)."""
SUN_MODULE = "astral"


def parse_clock_window(text: str) -> tuple[int, int]:
    """`HH:MM-HH:MM` (UTC) as (start, end) in minutes of the day; an end at or before the
    start wraps past midnight (`22:00-02:00`), `24:00` is the end of the day."""
    expected = f"expected a UTC window HH:MM-HH:MM (e.g. 06:00-18:30), got {text!r}"
    start, sep, end = text.strip().partition("-")
    if not sep:
        raise ValueError(expected)
    minutes = []
    for part in (start, end):
        hh, colon, mm = part.strip().partition(":")
        if not (colon and hh.isdigit() and mm.isdigit() and len(mm) == 2 and len(hh) <= 2):
            raise ValueError(expected)
        h, m = int(hh), int(mm)
        if m > 59 or h > 24 or (h == 24 and m > 0):
            raise ValueError(expected)
        minutes.append(h * 60 + m)
    if minutes[0] == MINUTES_PER_DAY:
        raise ValueError(f"{expected}: a window cannot start at 24:00 (write 00:00)")
    if minutes[0] == minutes[1]:
        raise ValueError(f"{expected}: a window of no length")
    return minutes[0], minutes[1]


class ScheduleConfig(Section):
    """When the trap records. No rule given (the default): always, as without a schedule.
    With several, it records where all of them agree: inside a periodic window, inside a
    clock window, and away from sunrise and sunset."""

    every_min: Annotated[float, msgspec.Meta(ge=0, le=MINUTES_PER_DAY)] = 0.0
    """A periodic window every this many minutes (0: none), starting on each multiple of it
    counted from 00:00 UTC (60: on the hour), plus offset_min. Fractions are seconds (0.1
    is 6 s; the tests' windows)."""
    for_min: Annotated[float, msgspec.Meta(ge=0, le=MINUTES_PER_DAY)] = 0.0
    """Length of each periodic window (0 < for_min <= every_min)."""
    offset_min: Annotated[float, msgspec.Meta(ge=0, le=MINUTES_PER_DAY)] = 0.0
    """Periodic windows start this long after each multiple of every_min (< every_min)."""
    windows: list[str] = msgspec.field(default_factory=list)
    """Daily clock windows, UTC, `HH:MM-HH:MM` (`22:00-02:00` wraps past midnight; `24:00`
    ends the day); empty: no clock rule."""
    sun_margin_min: Annotated[float, msgspec.Meta(ge=0, le=360)] = 0.0
    """Skip this many minutes either side of sunrise and sunset at latitude/longitude (0:
    no sun rule). Needs the `sun` extra (pip install 'trapflow[sun]')."""
    latitude: Annotated[float, msgspec.Meta(ge=-90, le=90)] | None = None
    """Degrees north of the trap (for the sun rule)."""
    longitude: Annotated[float, msgspec.Meta(ge=-180, le=180)] | None = None
    """Degrees east of the trap (for the sun rule)."""
    between: Literal["idle", "poweroff"] = "idle"
    """Between windows: `idle` (the board stays up, the pipeline stopped) or `poweroff` (set
    the wake alarm of `power:` for the next window, then power off)."""

    def __post_init__(self) -> None:
        if self.every_min > 0:
            if not 0 < self.for_min <= self.every_min:
                raise ValueError(f"schedule: expected 0 < for_min <= every_min "
                                 f"({self.every_min:g}), got for_min {self.for_min:g}")
            if self.offset_min >= self.every_min:
                raise ValueError(f"schedule: expected offset_min < every_min "
                                 f"({self.every_min:g}), got {self.offset_min:g}")
        elif self.for_min > 0 or self.offset_min > 0:
            raise ValueError("schedule: for_min and offset_min need every_min > 0")
        self.clock_windows()  # each window parses
        if self.sun_margin_min > 0:
            if self.latitude is None or self.longitude is None:
                raise ValueError("schedule: sun_margin_min needs latitude and longitude")
            if importlib.util.find_spec(SUN_MODULE) is None:
                raise ValueError(
                    f"schedule: sun_margin_min needs the sun's position: install the "
                    f"'{SUN_EXTRA}' extra (pip install 'trapflow[{SUN_EXTRA}]')")

    def clock_windows(self) -> list[tuple[int, int]]:
        """The clock windows as (start, end) minutes of the UTC day (end <= start: wraps)."""
        return [parse_clock_window(w) for w in self.windows]

    @property
    def enabled(self) -> bool:
        """Whether any rule is given (otherwise the trap always records)."""
        return self.every_min > 0 or bool(self.windows) or self.sun_margin_min > 0


class PowerConfig(Section):
    """How the board wakes for the next recording window and powers off (`schedule.between:
    poweroff`)."""

    wake: Literal["rtc", "command", "none"] = "rtc"
    """`rtc`: the board's RTC wake alarm (rtc_path); `command`: run wake_command (a power
    board's tool); `none`: no alarm, so `between: poweroff` is refused."""
    rtc_path: str = "/sys/class/rtc/rtc0/wakealarm"
    """The RTC's wake alarm: 0 is written to clear it, then the epoch second to wake at
    (writable by the service: a udev rule or root)."""
    wake_command: str = ""
    """Command that sets the wake time, `{epoch}` replaced by its epoch second (UTC), e.g.
    `wittypi-schedule --at {epoch}`; split like a shell line, run without a shell."""
    poweroff_command: str = "systemctl poweroff"
    """Command that powers the board off once the alarm is set."""
    boot_margin_s: Annotated[float, msgspec.Meta(ge=0, le=3600)] = 90.0
    """Wake this long before a window starts (boot, then the pipeline's start)."""
    min_off_s: Annotated[float, msgspec.Meta(ge=0, le=86400)] = 300.0
    """Power off only when the board would stay off at least this long (after boot_margin_s);
    a shorter gap is waited out idle."""

    def __post_init__(self) -> None:
        if self.wake == "command":
            fields = {f for _, f, _, _ in string.Formatter().parse(self.wake_command) if f}
            if "epoch" not in fields or fields - {"epoch"}:
                raise ValueError(f"power: wake_command must name {{epoch}} and nothing else, "
                                 f"got {self.wake_command!r}")
        if not self.poweroff_command.strip():
            raise ValueError("power: poweroff_command is empty")
