"""The degradation ladder's decisions without sensors or clocks: thresholds per level,
hysteresis, dwell, several triggers at once, missing readings, operator force, config
errors naming the YAML path."""

from __future__ import annotations

from typing import Any

import msgspec
import pytest

from trapflow.config import schema as config
from trapflow.config.ladder import AUTO, LadderConfig, LevelConfig, PoolLevel, TriggerConfig
from trapflow.errors import ConfigError
from trapflow.supervisor.ladder import Ladder, Readings

LEVELS = ("ir_slowed", "mono_vo", "vo_health")


def trig(sensor: Any, enter: tuple[float, ...], release: tuple[float, ...],
         dwell_s: float = 0.0, pool: str = "") -> TriggerConfig:
    return TriggerConfig(sensor=sensor, pool=pool, enter=dict(zip(LEVELS, enter, strict=True)),
                         release=dict(zip(LEVELS, release, strict=True)),
                         dwell_s=dwell_s)


TEMP = trig("cpu_temp_c", (75, 80, 85), (70, 75, 80))


def ladder(*triggers: TriggerConfig) -> Ladder:
    return Ladder(LadderConfig(triggers=list(triggers or (TEMP,))))


def run(lad: Ladder, seq: list[tuple[float, Readings]]) -> list[str]:
    """The level after each (now, readings)."""
    return [lad.update(r, now).level for now, r in seq]


def temps(*values: float | None, dt: float = 1.0) -> list[tuple[float, Readings]]:
    return [(i * dt, Readings(cpu_temp_c=v)) for i, v in enumerate(values)]


# --- one trigger: thresholds, one step at a time, hysteresis ------------------------------


@pytest.mark.parametrize(("values", "levels"), [
    # below every threshold: full
    ((40, 60, 74.9), ["full", "full", "full"]),
    # at the threshold enters (>=); one level per reading even when far past several
    ((75, 76), ["ir_slowed", "ir_slowed"]),
    ((90, 90, 90, 90), ["ir_slowed", "mono_vo", "vo_health", "vo_health"]),
    # hysteresis: 72 is below enter (75) but above release (70): the level holds
    ((76, 72, 72, 70.5), ["ir_slowed"] * 4),
    # back below release: down one level per reading
    ((76, 69, 69), ["ir_slowed", "full", "full"]),
    ((90, 90, 90, 40, 40, 40, 40), ["ir_slowed", "mono_vo", "vo_health", "mono_vo",
                                     "ir_slowed", "full", "full"]),
    # at mono_vo, 78 is under mono_vo's release (75)? no: above it, so mono_vo holds
    ((81, 81, 78, 78), ["ir_slowed", "mono_vo", "mono_vo", "mono_vo"]),
    # 72 at mono_vo: released from mono_vo (75) but held by ir_slowed (release 70)
    ((81, 81, 72, 72, 72), ["ir_slowed", "mono_vo", "ir_slowed", "ir_slowed", "ir_slowed"]),
])
def test_one_trigger_steps_with_hysteresis(values: tuple[float, ...],
                                           levels: list[str]) -> None:
    assert run(ladder(), temps(*values)) == levels


@pytest.mark.parametrize(("dwell", "values", "levels"), [
    # a spike shorter than the dwell moves nothing
    (3.0, (90, 90, 40, 40, 40), ["full"] * 5),
    # past the dwell: up; the next level needs a fresh dwell at the new level
    (2.0, (90, 90, 90, 90, 90, 90, 90),
     ["full", "full", "ir_slowed", "ir_slowed", "ir_slowed", "mono_vo", "mono_vo"]),
    # down needs the dwell too; a rise in between restarts it
    (2.0, (76, 76, 76, 60, 60, 76, 60, 60, 60),
     ["full", "full", "ir_slowed", "ir_slowed", "ir_slowed", "ir_slowed", "ir_slowed",
      "ir_slowed", "full"]),
])
def test_dwell_before_stepping_up_or_down(dwell: float, values: tuple[float, ...],
                                          levels: list[str]) -> None:
    t = trig("cpu_temp_c", (75, 80, 85), (70, 75, 80), dwell_s=dwell)
    assert run(ladder(t), temps(*values)) == levels


@pytest.mark.parametrize(("trigger", "readings", "levels"), [
    # lower is worse: free disk and battery voltage
    (trig("disk_free_mb", (2000, 1000, 500), (2500, 1500, 750)),
     [Readings(disk_free_mb=v) for v in (5000, 1900, 2400, 2600)],
     ["full", "ir_slowed", "ir_slowed", "full"]),
    (trig("battery_v", (11.8, 11.5, 11.2), (12.0, 11.7, 11.4)),
     [Readings(battery_v=v) for v in (11.1, 11.1, 11.1, 11.3)],
     ["ir_slowed", "mono_vo", "vo_health", "vo_health"]),
    (trig("disk_free_pct", (10, 5, 2), (12, 7, 3)),
     [Readings(disk_free_pct=v) for v in (50, 9.9)], ["full", "ir_slowed"]),
    # a pool's backlog and latency, by pool
    (trig("pool_backlog", (10, 20, 40), (5, 10, 20), pool="stereo"),
     [Readings(pool_backlog={"mono": 99}), Readings(pool_backlog={"stereo": 12})],
     ["full", "ir_slowed"]),
    (trig("pool_latency_ms", (500, 1000, 2000), (300, 600, 1200), pool="vo"),
     [Readings(pool_latency_ms={"vo": 1500}), Readings(pool_latency_ms={"vo": 1500})],
     ["ir_slowed", "mono_vo"]),
    (trig("load_per_core", (1.5, 2, 3), (1.2, 1.5, 2)),
     [Readings(load_per_core=v) for v in (1.6, 1.3, 1.1)], ["ir_slowed", "ir_slowed", "full"]),
    (trig("outbox_backlog", (100, 200, 300), (50, 150, 250)),
     [Readings(outbox_backlog=v) for v in (150, 160)], ["ir_slowed", "ir_slowed"]),
])
def test_every_sensor_kind(trigger: TriggerConfig, readings: list[Readings],
                           levels: list[str]) -> None:
    assert run(ladder(trigger), [(float(i), r) for i, r in enumerate(readings)]) == levels


# --- several triggers, missing readings ----------------------------------------------------


DISK = trig("disk_free_mb", (2000, 1000, 500), (2500, 1500, 750))


@pytest.mark.parametrize(("readings", "levels"), [
    # either trigger moves it up; the worse of the two decides how far
    ([Readings(cpu_temp_c=40, disk_free_mb=800)] * 3, ["ir_slowed", "mono_vo", "mono_vo"]),
    # down only when every trigger lets go: the disk still holds ir_slowed
    ([Readings(cpu_temp_c=76, disk_free_mb=1900), Readings(cpu_temp_c=40, disk_free_mb=2200)],
     ["ir_slowed", "ir_slowed"]),
    ([Readings(cpu_temp_c=76, disk_free_mb=1900), Readings(cpu_temp_c=40, disk_free_mb=2600)],
     ["ir_slowed", "full"]),
    # a missing reading never moves it up ...
    ([Readings(), Readings(disk_free_mb=None, cpu_temp_c=None)], ["full", "full"]),
    # ... and a trigger whose sensor goes missing no longer holds the level
    ([Readings(cpu_temp_c=76), Readings(disk_free_mb=5000)], ["ir_slowed", "full"]),
    # NaN is a missing reading
    ([Readings(cpu_temp_c=float("nan"))], ["full"]),
])
def test_several_triggers_and_missing_readings(readings: list[Readings],
                                               levels: list[str]) -> None:
    lad = ladder(TEMP, DISK)
    assert [lad.update(r, float(i)).level for i, r in enumerate(readings)] == levels


def test_a_trigger_with_thresholds_on_some_levels_only() -> None:
    """A backlog that may only slow the recogniser never takes the ladder past ir_slowed."""
    t = TriggerConfig(sensor="pool_backlog", pool="stereo", enter={"ir_slowed": 5},
                      release={"ir_slowed": 2}, dwell_s=0)
    lad = ladder(t)
    got = [lad.update(Readings(pool_backlog={"stereo": 100}), float(i)).level
           for i in range(4)]
    assert got == ["ir_slowed"] * 4


def test_step_says_which_trigger_value_and_threshold() -> None:
    lad = ladder(TEMP, DISK)
    step = lad.update(Readings(cpu_temp_c=85.0, disk_free_mb=5000), 0.0)
    assert step.changed and step.level == "ir_slowed" and step.index == 1
    assert (step.trigger, step.value, step.threshold) == ("cpu_temp_c", 85.0, 75.0)
    assert step.reason == "full -> ir_slowed: cpu_temp_c 85C >= 75C for 0 s"
    same = lad.update(Readings(cpu_temp_c=72.0), 1.0)
    assert not same.changed and same.reason == step.reason
    down = lad.update(Readings(cpu_temp_c=40.0), 2.0)
    assert down.changed and down.level == "full"
    assert down.reason == "ir_slowed -> full: cpu_temp_c 40C < 70C for 0 s, released"
    assert (down.trigger, down.value, down.threshold) == ("cpu_temp_c", 40.0, 70.0)
    assert lad.changes == 2


# --- operator force -----------------------------------------------------------------------


def test_force_holds_a_level_until_auto() -> None:
    lad = ladder()
    step = lad.force("vo_health", 0.0)
    assert step.changed and step.level == "vo_health" and "forced" in step.reason
    # cold, but forced: it stays
    assert run(lad, temps(40, 40, 40)) == ["vo_health"] * 3
    assert not lad.force(AUTO, 3.0).changed
    # auto: the triggers decide again, one step per reading from where it is
    assert run(lad, [(4.0 + i, Readings(cpu_temp_c=40)) for i in range(4)]) == [
        "mono_vo", "ir_slowed", "full", "full"]


def test_force_unknown_level_names_the_levels() -> None:
    with pytest.raises(ValueError, match="expected one of full, ir_slowed, mono_vo, "
                                         "vo_health or auto"):
        ladder().force("warp", 0.0)


def test_plan_per_level() -> None:
    lad = ladder()
    assert lad.plan() == {}
    assert lad.plan("ir_slowed") == {"stereo": PoolLevel(min_interval_s=5.0)}
    assert lad.plan("vo_health")["mono"].active is False


# --- config --------------------------------------------------------------------------------


def test_defaults_are_enabled_with_four_levels() -> None:
    cfg = config.Config().ladder
    assert cfg.enabled and [lv.name for lv in cfg.levels] == ["full", *LEVELS]
    assert {t.sensor for t in cfg.triggers} >= {"cpu_temp_c", "disk_free_mb"}


@pytest.mark.parametrize(("ladder_data", "error"), [
    ({"levels": [{"name": "full"}, {"name": "full"}]}, "distinct names"),
    ({"levels": [{"name": "full"}, {"name": "auto"}]}, "distinct names"),
    ({"levels": []}, "at `$.ladder.levels`"),
    ({"levels": [{"name": "full", "pools": {"stereo": {"min_interval_s": -1}}}]},
     "at `$.ladder.levels[0].pools[...].min_interval_s`"),
    ({"triggers": [{"sensor": "humidity"}]}, "at `$.ladder.triggers[0].sensor`"),
    ({"triggers": [{"sensor": "pool_backlog", "enter": {}, "release": {}}]},
     "pool is required"),
    ({"triggers": [{"sensor": "cpu_temp_c", "pool": "mono"}]}, "refused for other sensors"),
    ({"triggers": [{"sensor": "cpu_temp_c", "enter": {"ir_slowed": 70},
                    "release": {}}]}, "release must name the same levels"),
    ({"triggers": [{"sensor": "cpu_temp_c", "enter": {"ir_slowed": 70},
                    "release": {"ir_slowed": 75}}]}, "release must be below enter"),
    ({"triggers": [{"sensor": "battery_v", "enter": {"ir_slowed": 11},
                    "release": {"ir_slowed": 10}}]}, "release must be above enter"),
    ({"triggers": [{"sensor": "cpu_temp_c", "enter": {"full": 70},
                    "release": {"full": 60}}]}, "the first level is entered only"),
    ({"triggers": [{"sensor": "cpu_temp_c", "enter": {"ir_slowed": 80, "mono_vo": 70},
                    "release": {"ir_slowed": 75, "mono_vo": 65}}]},
     "enter thresholds must rise"),
    ({"triggers": [{"sensor": "cpu_temp_c", "dwell_s": -1}]},
     "at `$.ladder.triggers[0].dwell_s`"),
    ({"sensors": {"battery_unit": "kV"}}, "at `$.ladder.sensors.battery_unit`"),
    ({"interval_s": 0}, "at `$.ladder.interval_s`"),
    ({"colour": "red"}, "unknown field `colour` - at `$.ladder`"),
])
def test_config_errors_name_the_path(ladder_data: dict[str, Any], error: str) -> None:
    with pytest.raises(ConfigError, match="ladder") as info:
        config.from_data({"ladder": ladder_data}, "trap.yaml")
    assert error in str(info.value)
    assert str(info.value).startswith("trap.yaml: ")


def test_config_round_trips_through_yaml_data() -> None:
    cfg = LadderConfig(levels=[LevelConfig(name="full"), LevelConfig(
        name="slow", pools={"stereo": PoolLevel(min_interval_s=2.0)})],
        triggers=[TriggerConfig(sensor="cpu_temp_c", enter={"slow": 60},
                                release={"slow": 55})])
    again = config.from_data({"ladder": msgspec.to_builtins(cfg)}).ladder
    assert again == cfg
