"""Wall-clock steps, told from the steady drift of an NTP slew: pure, callers pass both
clocks' readings.

trapflow measures every duration on the monotonic clock and uses the wall clock as a label
only, so a step (an NTP fix after a boot without a real-time clock, an operator's `date
-s`) changes nothing but the timestamps written after it. It is still worth saying once:
timestamps before and after a step do not subtract, and the surface and the exports must
know where a run's clock jumped. The difference wall - monotonic moves by at most 500 ppm
under a slewing NTP (0.5 ms a second); a change of more than STEP_S between two readings
is a step.
"""

from __future__ import annotations

from dataclasses import dataclass, field

STEP_S = 1.0
"""A change of wall - monotonic above this between two readings is a step (seconds)."""


@dataclass
class ClockSteps:
    """Feed it (wall, monotonic) readings in seconds; it returns each step once."""

    threshold_s: float = STEP_S
    steps: list[tuple[float, float]] = field(default_factory=list)  # (monotonic s, step s)
    _offset: float | None = None

    def observe(self, wall_s: float, mono_s: float) -> float | None:
        """The step since the last reading (seconds, + forward), or None."""
        offset = wall_s - mono_s
        last, self._offset = self._offset, offset
        if last is None or abs(offset - last) <= self.threshold_s:
            return None
        self.steps.append((mono_s, offset - last))
        return offset - last
