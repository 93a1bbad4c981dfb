"""The degradation ladder's configuration: levels, triggers, sensors (config structs only).

Imported by trapflow.config.schema, so it imports nothing of the runtime;
trapflow.supervisor.ladder (the pure ladder itself) takes its names from here.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

import msgspec

AUTO = "auto"  # LevelRequest's name for "the triggers decide again"

# Readings where a lower value is worse (the rest: higher is worse).
LOWER_IS_WORSE = frozenset({"disk_free_mb", "disk_free_pct", "battery_v"})
POOL_SENSORS = frozenset({"pool_backlog", "pool_latency_ms"})
Sensor = Literal["cpu_temp_c", "load_per_core", "pool_backlog", "pool_latency_ms",
                 "disk_free_mb", "disk_free_pct", "outbox_backlog", "battery_v"]
UNITS = {"cpu_temp_c": "C", "load_per_core": "", "pool_backlog": " pairs",
         "pool_latency_ms": " ms", "disk_free_mb": " MB", "disk_free_pct": " %",
         "outbox_backlog": " records", "battery_v": " V"}

Name = Annotated[str, msgspec.Meta(min_length=1, max_length=64,
                                   pattern=r"^[A-Za-z_][A-Za-z0-9_.\-]*$")]


class _Section(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    pass


class PoolLevel(_Section):
    """What one level does to one pool (pools a level does not name run as configured)."""

    active: bool = True
    """False: the pool is deactivated at this level (its pairs counted dropped while
    inactive)."""
    min_interval_s: Annotated[float, msgspec.Meta(ge=0, le=3600)] = 0.0
    """At most one pair every this many seconds (0: no limit); the pairs skipped are
    counted as dropped by the level."""


class LevelConfig(_Section):
    """One rung of the ladder."""

    name: Name
    """The level's name, as `trapflow level NAME`, the status line and the ledger show it."""
    pools: dict[Name, PoolLevel] = {}
    """pool -> what the level does to it; pools not named run as configured."""


class TriggerConfig(_Section):
    """One sensor, its thresholds per level and its dwell."""

    sensor: Sensor
    """What is read: cpu_temp_c, load_per_core, pool_backlog (pairs), pool_latency_ms,
    disk_free_mb, disk_free_pct, outbox_backlog (records) or battery_v."""
    pool: str = ""
    """The pool whose backlog or latency is read (pool_backlog, pool_latency_ms only)."""
    enter: dict[Name, float] = {}
    """level -> the reading that enters it (at or above; at or below for free disk and
    battery voltage)."""
    release: dict[Name, float] = {}
    """level -> the reading back past which the level is left (the same levels as enter)."""
    dwell_s: Annotated[float, msgspec.Meta(ge=0, le=86400)] = 10.0
    """Seconds a reading must stay past a threshold before the ladder steps."""

    def __post_init__(self) -> None:
        if (self.sensor in POOL_SENSORS) != bool(self.pool):
            raise ValueError(f"trigger {self.sensor}: pool is required for pool_backlog and "
                             f"pool_latency_ms and refused for other sensors, got "
                             f"pool={self.pool!r}")
        if set(self.enter) != set(self.release):
            raise ValueError(f"trigger {self.sensor}: release must name the same levels as "
                             f"enter, got enter {sorted(self.enter)} and release "
                             f"{sorted(self.release)}")
        lower = self.sensor in LOWER_IS_WORSE
        for level, at in self.enter.items():
            back = self.release[level]
            if not (math.isfinite(at) and math.isfinite(back)):
                raise ValueError(f"trigger {self.sensor}: level {level}: expected finite "
                                 f"thresholds, got enter {at} and release {back}")
            if (back <= at) if lower else (back >= at):
                rel = "above" if lower else "below"
                raise ValueError(f"trigger {self.sensor}: level {level}: release must be "
                                 f"{rel} enter (hysteresis), got enter {at} and release "
                                 f"{back}")

    @property
    def key(self) -> str:
        """The trigger's name in reasons and the ledger: the sensor, and its pool."""
        return f"{self.sensor}:{self.pool}" if self.pool else self.sensor


def _default_levels() -> list[LevelConfig]:
    return [
        LevelConfig(name="full"),
        LevelConfig(name="ir_slowed", pools={"stereo": PoolLevel(min_interval_s=5.0)}),
        LevelConfig(name="mono_vo", pools={"stereo": PoolLevel(active=False),
                                           "tags": PoolLevel(active=False)}),
        LevelConfig(name="vo_health", pools={"mono": PoolLevel(active=False),
                                             "stereo": PoolLevel(active=False),
                                             "tags": PoolLevel(active=False)}),
    ]


def _default_triggers() -> list[TriggerConfig]:
    # Safe defaults for a Pi 5 on a long deployment: it throttles its clock from 80-85 C.
    # No load trigger by default: pools with the `latest` policy keep their cores busy by
    # design (a recogniser saturates its core and drops), so load is high when all is well.
    levels = ("ir_slowed", "mono_vo", "vo_health")

    def trig(sensor: Sensor, enter: tuple[float, ...], release: tuple[float, ...],
             dwell_s: float, pool: str = "") -> TriggerConfig:
        return TriggerConfig(sensor=sensor, pool=pool,
                             enter=dict(zip(levels, enter, strict=True)),
                             release=dict(zip(levels, release, strict=True)), dwell_s=dwell_s)

    return [
        trig("cpu_temp_c", (80.0, 85.0, 90.0), (75.0, 80.0, 85.0), 30.0),
        trig("disk_free_mb", (1000.0, 500.0, 250.0), (1500.0, 750.0, 400.0), 30.0),
        trig("outbox_backlog", (20000.0, 50000.0, 100000.0), (15000.0, 40000.0, 80000.0),
             60.0),
    ]


class SensorsConfig(_Section):
    """Where the sensors are read (trapflow.supervisor.sensors)."""

    temperature_path: str = "/sys/class/thermal/thermal_zone0/temp"
    """File holding the CPU temperature ("" = none)."""
    temperature_unit: Literal["mC", "C"] = "mC"
    """Unit of the number in temperature_path: millidegrees (sysfs) or degrees Celsius."""
    battery_path: str = ""
    """File holding the battery voltage, e.g. /sys/class/power_supply/BAT0/voltage_now
    ("" = none)."""
    battery_unit: Literal["V", "mV", "uV"] = "uV"
    """Unit of the number in battery_path (sysfs power_supply gives microvolts)."""


class LadderConfig(_Section):
    """The degradation ladder: levels, triggers, sensors."""

    enabled: bool = True
    """Read the sensors and step the levels; false: the pipeline always runs at full."""
    interval_s: Annotated[float, msgspec.Meta(ge=0.1, le=600)] = 1.0
    """Seconds between two readings of the sensors."""
    levels: Annotated[list[LevelConfig], msgspec.Meta(min_length=1, max_length=16)] = \
        msgspec.field(default_factory=_default_levels)
    """From full (first) to the most degraded (last)."""
    triggers: Annotated[list[TriggerConfig], msgspec.Meta(max_length=64)] = \
        msgspec.field(default_factory=_default_triggers)
    """What moves the ladder."""
    sensors: SensorsConfig = msgspec.field(default_factory=SensorsConfig)

    def __post_init__(self) -> None:
        names = [lv.name for lv in self.levels]
        if len(set(names)) != len(names) or AUTO in names:
            raise ValueError(f"levels: expected distinct names other than {AUTO!r}, got "
                             f"{names}")
        for i, t in enumerate(self.triggers):
            for level in t.enter:
                if level not in names[1:]:
                    raise ValueError(f"triggers[{i}] ({t.key}): expected levels among "
                                     f"{names[1:]} (the first level is entered only by "
                                     f"release), got {level!r}")
            named = [n for n in names if n in t.enter]
            order = [t.enter[n] for n in named]
            lower = t.sensor in LOWER_IS_WORSE
            if order != sorted(order, reverse=lower):
                how = "fall" if lower else "rise"
                raise ValueError(f"triggers[{i}] ({t.key}): enter thresholds must {how} "
                                 f"with the levels (worse reading, deeper level), got "
                                 f"{dict(zip(named, order, strict=True))}")
