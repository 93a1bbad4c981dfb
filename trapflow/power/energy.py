"""Energy estimate of a deployment, pure: CPU seconds per role over a wall interval and a
per-board power model give watts, watt-hours per day and days on a battery."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

HOURS_PER_DAY = 24.0


@dataclass(frozen=True)
class Board:
    """A board's power model: idle, plus linear terms for busy cores, GPU and cameras."""

    name: str
    idle_w: float
    """Whole board idle, OS up, no USB load."""
    core_w: float
    """Added per fully busy CPU core."""
    cores: int
    """CPU cores: busy time above cores x wall time cannot draw more."""
    camera_w: float
    """Per camera streaming."""
    gpu_w: float = 0.0
    """Added by a fully busy GPU."""
    lamp_w: float = 0.0
    """The trap's lamp while on."""
    off_w: float = 0.0
    """Powered off between recording windows, waiting for the wake alarm."""

    def __post_init__(self) -> None:
        if min(self.idle_w, self.core_w, self.camera_w, self.gpu_w, self.lamp_w,
               self.off_w) < 0:
            raise ValueError(f"board {self.name!r}: expected watts >= 0")
        if self.cores < 1:
            raise ValueError(f"board {self.name!r}: expected cores >= 1, got {self.cores}")


# Rough figures of the order published for each board (vendor product briefs and power
# modes, independent idle and stress measurements of the Pi 5: about 2.7 W idle, about 8 W
# with four cores busy); they are starting points, configurable, and a deployment should
# replace them with a measurement of its own board, cameras and lamp. Off: a Pi 5 halted
# with POWER_OFF_ON_HALT=1 in its EEPROM config draws about 0.01 W (the RTC keeps its alarm;
# with the default setting a halted Pi 5 draws over 1 W); the Orin Nano's figure is a rough
# guess for a carrier board that cuts the module's power, to be measured.
BOARDS: dict[str, Board] = {
    "pi5": Board("pi5", idle_w=2.7, core_w=1.3, cores=4, camera_w=0.2, off_w=0.01),
    # Orin Nano: the module's 7 W / 15 W power modes over ~4.5 W idle (developer kit).
    "orin_nano": Board("orin_nano", idle_w=4.5, core_w=0.8, cores=6, camera_w=0.2,
                       gpu_w=5.0, off_w=0.1),
}

RECORDING_CPU_S_PER_HOUR: dict[str, float] = {"pipeline": 898.0}
"""CPU seconds an hour of recording when no run is given to plan from: the whole pipeline
on its defaults (motion-gated recognisers) on the default synthetic world, as measured in
docs/benchmarks.md ("Motion gate, whole pipelines"), about 0.25 busy cores."""


@dataclass(frozen=True)
class Estimate:
    """Power and endurance of one run."""

    watts: float
    wh_per_day: float
    busy_cores: float
    """Mean CPU cores busy (CPU seconds / wall seconds, capped at the board's cores)."""
    cpu_s_per_hour: dict[str, float]
    """CPU seconds per role per hour of wall time."""

    def days(self, battery_wh: float, usable: float = 1.0) -> float:
        """Days on a battery of `battery_wh` of which `usable` (0..1] can be drawn."""
        return days_on_battery(self.wh_per_day, battery_wh, usable)


def estimate(board: Board, cpu_s: Mapping[str, float], wall_s: float, *, cameras: int = 2,
             gpu_s: float = 0.0, lamp_duty: float = 0.0) -> Estimate:
    """Watts over `wall_s` seconds in which each role (pool, process) used `cpu_s[role]`
    CPU seconds; the GPU was busy `gpu_s` seconds and the lamp on `lamp_duty` (0..1) of it."""
    if not wall_s > 0:
        raise ValueError(f"energy: expected a wall interval > 0 s, got {wall_s}")
    if any(v < 0 for v in cpu_s.values()) or gpu_s < 0 or cameras < 0:
        raise ValueError("energy: expected CPU seconds, GPU seconds and cameras >= 0")
    if not 0 <= lamp_duty <= 1:
        raise ValueError(f"energy: expected a lamp duty of 0..1, got {lamp_duty}")
    busy = min(sum(cpu_s.values()) / wall_s, float(board.cores))
    gpu = min(gpu_s / wall_s, 1.0)
    watts = (board.idle_w + board.core_w * busy + board.gpu_w * gpu
             + board.camera_w * cameras + board.lamp_w * lamp_duty)
    per_hour = {role: s * 3600.0 / wall_s for role, s in cpu_s.items()}
    return Estimate(watts=watts, wh_per_day=watts * HOURS_PER_DAY, busy_cores=busy,
                    cpu_s_per_hour=per_hour)


def days_on_battery(wh_per_day: float, battery_wh: float, usable: float = 1.0) -> float:
    """Days a battery of `battery_wh` lasts at `wh_per_day`, drawing `usable` of it."""
    if not (wh_per_day > 0 and battery_wh >= 0 and 0 < usable <= 1):
        raise ValueError(f"energy: expected Wh/day > 0, battery >= 0 Wh, 0 < usable <= 1, "
                         f"got {wh_per_day}, {battery_wh}, {usable}")
    return battery_wh * usable / wh_per_day


def cpu_from_rates(per_pair_s: Mapping[str, float], pairs_per_s: Mapping[str, float],
                   wall_s: float) -> dict[str, float]:
    """CPU seconds per role from its cost per pair and the pairs it gets per second (a
    scenario: the original trap's per-frame costs at the rate each recogniser is fed)."""
    return {role: per_pair_s[role] * pairs_per_s.get(role, 0.0) * wall_s
            for role in per_pair_s}
