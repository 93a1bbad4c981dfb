"""The energy estimate: watts, Wh per day and days per battery from CPU seconds."""

from __future__ import annotations

import pytest

from trapflow.power.energy import BOARDS, Board, cpu_from_rates, days_on_battery, estimate

PI5 = BOARDS["pi5"]
ORIN = BOARDS["orin_nano"]
HOUR = 3600.0


@pytest.mark.parametrize(("board", "cpu_s", "cameras", "gpu_s", "lamp", "watts"), [
    (PI5, {}, 0, 0.0, 0.0, 2.7),  # idle, no cameras: the board's floor
    (PI5, {}, 2, 0.0, 0.0, 3.1),  # two cameras streaming, nothing running
    (PI5, {"mono": 1800.0, "vo": 1800.0}, 2, 0.0, 0.0, 4.4),  # one core busy over the hour
    (PI5, {"mono": 4 * HOUR, "stereo": 4 * HOUR}, 2, 0.0, 0.0, 8.3),  # capped at 4 cores
    (ORIN, {"mono": HOUR}, 2, HOUR / 2, 0.0, 8.2),  # one core, GPU half the time
    (Board("lit", idle_w=3.0, core_w=1.0, cores=4, camera_w=0.0, lamp_w=4.0), {}, 0, 0.0,
     0.25, 4.0),  # a 4 W lamp on a quarter of the time
])
def test_watts(board: Board, cpu_s: dict[str, float], cameras: int, gpu_s: float, lamp: float,
               watts: float) -> None:
    e = estimate(board, cpu_s, HOUR, cameras=cameras, gpu_s=gpu_s, lamp_duty=lamp)
    assert e.watts == pytest.approx(watts)
    assert e.wh_per_day == pytest.approx(24 * watts)


def test_cpu_per_hour_per_role() -> None:
    e = estimate(PI5, {"mono": 60.0, "vo": 600.0}, 600.0)
    assert e.cpu_s_per_hour == pytest.approx({"mono": 360.0, "vo": 3600.0})
    assert e.busy_cores == pytest.approx(1.1)


@pytest.mark.parametrize(("wh_per_day", "battery_wh", "usable", "days"), [
    (100.0, 1000.0, 1.0, 10.0),  # the whole battery
    (100.0, 1000.0, 0.8, 8.0),  # a lead-acid or cold lithium battery: 80 % usable
    (74.4, 2232.0, 1.0, 30.0),  # a Pi 5 at 3.1 W: a month on 2.2 kWh
])
def test_days_on_battery(wh_per_day: float, battery_wh: float, usable: float, days: float
                         ) -> None:
    assert days_on_battery(wh_per_day, battery_wh, usable) == pytest.approx(days)


def test_the_original_trap_as_a_scenario() -> None:
    """The ROS 2 trap's measured costs per frame on a Pi 5 (mono 0.060 s, stereo 10.7 s):
    the stereo classifier fed once a minute adds 0.18 busy cores."""
    cpu = cpu_from_rates({"mono": 0.060, "stereo": 10.7}, {"mono": 1.0, "stereo": 1 / 60},
                         HOUR)
    assert cpu == pytest.approx({"mono": 216.0, "stereo": 642.0})
    e = estimate(PI5, cpu, HOUR)
    assert e.busy_cores == pytest.approx(858.0 / HOUR)
    assert e.days(1000.0) == pytest.approx(1000.0 / (24 * (3.1 + 1.3 * 858.0 / HOUR)))


@pytest.mark.parametrize(("call", "error"), [
    (lambda: estimate(PI5, {}, 0.0), "wall interval > 0 s"),  # no interval
    (lambda: estimate(PI5, {"mono": -1.0}, 1.0), "CPU seconds"),  # negative CPU time
    (lambda: estimate(PI5, {}, 1.0, lamp_duty=1.5), "lamp duty of 0..1"),  # lamp over 100 %
    (lambda: days_on_battery(0.0, 100.0), "Wh/day > 0"),  # nothing drawn: infinite days
    (lambda: Board("x", idle_w=-1.0, core_w=1.0, cores=4, camera_w=0.0), "watts >= 0"),
    (lambda: Board("x", idle_w=1.0, core_w=1.0, cores=0, camera_w=0.0), "cores >= 1"),
])
def test_rejects(call: object, error: str) -> None:
    with pytest.raises(ValueError, match=error):
        call()  # type: ignore[operator]
