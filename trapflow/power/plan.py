"""What a schedule costs a battery, pure (`trapflow plan`): the day split into recording,
booting, idle and off, each at its draw from the same board model as ledger.json's energy
line (trapflow.power.energy), so that with no schedule the plan's Wh a day is the ledger's.

Between two windows the board waits up (`idle`: the board's idle draw, the cameras off), or
powers off: woken `boot_margin_s` before the next window (booting: idle and one busy core)
and off the rest (`Board.off_w`); a gap too short to power off (trapflow.power.schedule's
`between`) is waited up, as the supervisor does.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping
from dataclasses import dataclass

from trapflow.power.energy import Board, days_on_battery, estimate
from trapflow.power.schedule import DAY_S, Idle, Schedule, Verdict, between, windows

BITS_PER_BYTE = 10  # the modem's framing: a start and a stop bit


@dataclass(frozen=True)
class DaySplit:
    """Seconds a day in each state, the mean over the days planned."""

    windows: float
    """Windows begun a day."""
    recording_s: float
    booting_s: float = 0.0
    idle_s: float = 0.0
    off_s: float = 0.0


def split_day(s: Schedule | None, day: dt.date, days: int, mode: str, boot_margin_s: float,
              min_off_s: float) -> DaySplit:
    """The mean day over `days` UTC days from `day`: each window begun in them, and the gap
    after it to the next window, booked as the supervisor spends it."""
    if s is None:
        return DaySplit(windows=1.0, recording_s=DAY_S)
    lo = (day - dt.date(1970, 1, 1)).days * DAY_S
    hi = lo + days * DAY_S
    found = windows(s, lo - DAY_S, hi + 9 * DAY_S)
    rec = boot = idle = off = 0.0
    begun = 0
    for (a, b), nxt in zip(found, [*found[1:], None], strict=True):
        if not lo <= a < hi:
            continue
        begun += 1
        rec += b - a
        if nxt is None:
            continue
        gap = nxt[0] - b
        action = between(Verdict(False, None, nxt[0]), b, mode, boot_margin_s, min_off_s)
        if isinstance(action, Idle):
            idle += gap
        else:
            on = nxt[0] - action.wake_at
            boot += on
            off += gap - on
    return DaySplit(begun / days, rec / days, boot / days, idle / days, off / days)


@dataclass(frozen=True)
class Plan:
    """A schedule's draw and endurance."""

    split: DaySplit
    recording_w: float
    booting_w: float
    idle_w: float
    off_w: float
    wh_per_day: float
    days: float | None
    """On the battery (None: no battery given)."""


def plan(board: Board, split: DaySplit, cpu_s_per_hour: Mapping[str, float], *,
         cameras: int = 2, battery_wh: float = 0.0, usable: float = 1.0) -> Plan:
    """Watts in each state and Wh a day; recording costs `cpu_s_per_hour` per role."""
    recording = estimate(board, cpu_s_per_hour, 3600.0, cameras=cameras).watts
    booting = board.idle_w + board.core_w
    wh = (split.recording_s * recording + split.booting_s * booting
          + split.idle_s * board.idle_w + split.off_s * board.off_w) / 3600.0
    days = days_on_battery(wh, battery_wh, usable) if battery_wh > 0 and wh > 0 else None
    return Plan(split, recording, booting, board.idle_w, board.off_w, wh, days)


def airtime_s(bytes_per_recording_hour: float, split: DaySplit, bit_rate: float) -> float:
    """Seconds a day the modem sends at the bytes a recording hour measured in a run."""
    return (bytes_per_recording_hour * split.recording_s / 3600.0 * BITS_PER_BYTE / bit_rate)

