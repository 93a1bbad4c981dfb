"""The degradation ladder, pure: sensor readings in, the level the pipeline should run at out.

No clocks, files or processes: callers pass `now` (monotonic seconds) and a Readings
snapshot. Levels go from full (first) to the most degraded (last); each says, per pool,
whether it runs and the least time between two pairs it is given. Triggers (CPU
temperature, load per core, a pool's backlog or latency, free disk, outbox backlog, battery
voltage) each name, per level, the reading that enters it and a separate one that releases
it (hysteresis), and how long a reading must stay past them (dwell) before the ladder moves.
The ladder moves one level at a time; a missing reading never moves it up. Its configuration
(levels, triggers, sensors) is in trapflow.config.ladder.

A trigger's demand at level L: the highest level whose enter threshold the reading is past
(up, when above L), else the highest level at or below L whose release threshold it is not
back past yet (it holds that level). Up by one when any trigger has demanded more than L
for its dwell; down by one when every trigger has demanded less than L for its dwell.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

from trapflow.config.ladder import (
    AUTO,
    LOWER_IS_WORSE,
    UNITS,
    LadderConfig,
    PoolLevel,
    TriggerConfig,
)


@dataclass(frozen=True)
class Readings:
    """One snapshot of the sensors; None (or absent from a pool map): not read."""

    cpu_temp_c: float | None = None
    load_per_core: float | None = None
    disk_free_mb: float | None = None
    disk_free_pct: float | None = None
    outbox_backlog: float | None = None
    battery_v: float | None = None
    pool_backlog: Mapping[str, float] = field(default_factory=dict)
    pool_latency_ms: Mapping[str, float] = field(default_factory=dict)

    def value(self, t: TriggerConfig) -> float | None:
        """The reading a trigger watches, or None."""
        if t.sensor == "pool_backlog":
            v = self.pool_backlog.get(t.pool)
        elif t.sensor == "pool_latency_ms":
            v = self.pool_latency_ms.get(t.pool)
        else:
            v = getattr(self, t.sensor)
        return None if v is None or not math.isfinite(v) else float(v)


@dataclass(frozen=True)
class Step:
    """The ladder's answer: the level now, whether it just changed, and why.

    trigger/value/threshold name what moved it (None when forced, or nothing moved it)."""

    level: str
    index: int
    changed: bool
    reason: str
    trigger: str | None = None
    value: float | None = None
    threshold: float | None = None


@dataclass
class _Watch:
    """One trigger's timers at the current level: since when it demanded up, or down."""

    up_since: float | None = None
    down_since: float | None = None


def _fmt(v: float) -> str:
    return f"{v:g}"


class Ladder:
    """The current level and the triggers' timers."""

    def __init__(self, cfg: LadderConfig) -> None:
        self.cfg = cfg
        self.names = [lv.name for lv in cfg.levels]
        self.index = 0
        self.forced = False
        self.reason = "start"
        self.changes = 0
        self._watch = [_Watch() for _ in cfg.triggers]
        self._held_by: int | None = None  # trigger that moved the ladder up last

    @property
    def level(self) -> str:
        return self.names[self.index]

    def plan(self, level: str | None = None) -> dict[str, PoolLevel]:
        """Per pool, what a level (default: the current one) does to it."""
        name = self.level if level is None else level
        return dict(self.cfg.levels[self.names.index(name)].pools)

    def _demand(self, t: TriggerConfig, v: float) -> tuple[int, float | None]:
        """The level this reading demands at the current level, and the threshold that
        decides it (see the module's docstring)."""
        lower = t.sensor in LOWER_IS_WORSE
        up = [(i, t.enter[n]) for i, n in enumerate(self.names)
              if n in t.enter and i > self.index
              and (v <= t.enter[n] if lower else v >= t.enter[n])]
        if up:
            return max(up)
        # Still held: not yet back past the release threshold of a level at or below.
        held = [(i, t.release[n]) for i, n in enumerate(self.names)
                if n in t.release and i <= self.index
                and (v < t.release[n] if lower else v > t.release[n])]
        if held:
            return max(held)
        below = [(i, t.release[n]) for i, n in enumerate(self.names)
                 if n in t.release and i <= self.index]
        return 0, (max(below)[1] if below else None)

    def update(self, readings: Readings, now: float) -> Step:
        """Take a snapshot of the sensors; step one level when a trigger's dwell is over."""
        demands: list[tuple[int, float | None, float | None]] = []
        for t, w in zip(self.cfg.triggers, self._watch, strict=True):
            v = readings.value(t)
            want, at = self._demand(t, v) if v is not None else (0, None)
            demands.append((want, v, at))
            if want > self.index:
                w.up_since = now if w.up_since is None else w.up_since
                w.down_since = None
            elif want < self.index:
                w.down_since = now if w.down_since is None else w.down_since
                w.up_since = None
            else:
                w.up_since = w.down_since = None
        if self.forced:
            return self._same()
        for i, (t, w) in enumerate(zip(self.cfg.triggers, self._watch, strict=True)):
            want, v, at = demands[i]
            if w.up_since is not None and now - w.up_since >= t.dwell_s and v is not None \
                    and at is not None:
                at = t.enter.get(self.names[self.index + 1], at)  # the rung entered
                cmp = "<=" if t.sensor in LOWER_IS_WORSE else ">="
                unit = UNITS[t.sensor]
                reason = (f"{t.key} {_fmt(v)}{unit} {cmp} {_fmt(at)}{unit} "
                          f"for {_fmt(t.dwell_s)} s")
                self._held_by = i
                return self._move(self.index + 1, reason, now, t.key, v, at)
        if self.index > 0 and all(
                w.down_since is not None and now - w.down_since >= t.dwell_s
                for t, w in zip(self.cfg.triggers, self._watch, strict=True)):
            by = self._held_by
            if by is not None and demands[by][1] is not None:
                t = self.cfg.triggers[by]
                _, v, at = demands[by]
                assert v is not None
                cmp = ">" if t.sensor in LOWER_IS_WORSE else "<"
                unit = UNITS[t.sensor]
                back = f" {cmp} {_fmt(at)}{unit}" if at is not None else ""
                reason = f"{t.key} {_fmt(v)}{unit}{back} for {_fmt(t.dwell_s)} s, released"
                return self._move(self.index - 1, reason, now, t.key, v, at)
            return self._move(self.index - 1, "every trigger released", now)
        return self._same()

    def force(self, level: str, now: float) -> Step:
        """An operator's order: a level by name (held until `auto`), or `auto` (the
        triggers decide again, from the level the ladder is at). ValueError names the
        levels for an unknown one."""
        if level == AUTO:
            self.forced = False
            self._reset_watches()
            self.reason = f"auto (from {self.level})"
            return Step(self.level, self.index, False, self.reason)
        if level not in self.names:
            raise ValueError(f"unknown level {level!r}: expected one of "
                             f"{', '.join(self.names)} or {AUTO}")
        self.forced = True
        if level == self.level:
            self.reason = "forced by the operator"
            return Step(self.level, self.index, False, self.reason)
        return self._move(self.names.index(level), "forced by the operator", now)

    def _same(self) -> Step:
        return Step(self.level, self.index, False, self.reason)

    def _reset_watches(self) -> None:
        for w in self._watch:
            w.up_since = w.down_since = None

    def _move(self, index: int, reason: str, now: float, trigger: str | None = None,
              value: float | None = None, threshold: float | None = None) -> Step:
        before = self.level
        self.index = index
        self.changes += 1
        self._reset_watches()  # the next step needs a fresh dwell at the new level
        if index == 0:
            self._held_by = None
        self.reason = f"{before} -> {self.level}: {reason}"
        return Step(self.level, index, True, self.reason, trigger, value, threshold)
