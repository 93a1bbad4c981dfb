"""trapflow.runtime.clock_step: a wall-clock step is told from an NTP slew, once."""

from __future__ import annotations

from trapflow.runtime.clock_step import ClockSteps


def test_steps_back_and_forward_are_said_once_and_a_slew_never() -> None:
    watch = ClockSteps()
    wall, got = 1_800_000_000.0, []
    for second in range(600):
        wall += 1.0005  # a slewing NTP: 500 ppm fast, never a step
        if second == 100:
            wall -= 3600.0
        if second == 400:
            wall += 86400.0
        step = watch.observe(wall, float(second))
        if step is not None:
            got.append((second, round(step, 1)))
    assert got == [(100, -3600.0), (400, 86400.0)]
    assert [round(s) for _, s in watch.steps] == [-3600, 86400]


def test_the_first_reading_is_no_step() -> None:
    assert ClockSteps().observe(5000.0, 3.0) is None
