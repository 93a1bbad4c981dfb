"""What the normalizer tells the motion gate, pure: whether the rig moves (from visual
odometry, with hysteresis) and when to say how many tracks are alive. The normalizer sends
it to the broker as a GateHint (trapflow.wire.gate_msgs) over the results link."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

# Said again this often while tracks are alive or the rig moves: the gate forgets a track
# not said alive for trapflow.gate.policy.TRACK_TTL_S (10 s), so a lost hint costs little.
HINT_INTERVAL_S = 1.0


@dataclass(frozen=True)
class RigConfig:
    """When visual odometry means the rig moves, and when it is still again."""

    moving_m_s: float = 0.05
    """Translation speed from which the rig moves (5 cm/s: a drifting or towed frame)."""
    moving_deg_s: float = 3.0
    """Rotation rate from which the rig moves."""
    moving_n: int = 3
    """VO results in a row past a threshold before the rig is said to move (noise)."""
    still_s: float = 2.0
    """Seconds below half of both thresholds before the rig is said to be still again."""

    def __post_init__(self) -> None:
        if not (self.moving_m_s > 0 and self.moving_deg_s > 0):
            raise ValueError(f"gate rig thresholds: expected > 0, got {self.moving_m_s} m/s "
                             f"and {self.moving_deg_s} deg/s")
        if not (self.moving_n >= 1 and self.still_s >= 0):
            raise ValueError(f"gate rig: expected moving_n >= 1 and still_s >= 0, got "
                             f"{self.moving_n} and {self.still_s}")


def rotation_deg(rotation: Sequence[float]) -> float:
    """The angle of a row-major 3x3 rotation, in degrees."""
    c = (rotation[0] + rotation[4] + rotation[8] - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


class RigMotion:
    """Moving or still, from VO's motion between consecutive pairs (capture times)."""

    def __init__(self, cfg: RigConfig | None = None) -> None:
        self.cfg = cfg or RigConfig()
        self.moving = False
        self._t: float | None = None  # capture time of the last VO result
        self._fast = 0  # results in a row past a threshold
        self._slow_since: float | None = None  # first of the results below half since

    def vo(self, t_s: float, ok: bool, rotation: Sequence[float],
           translation: Sequence[float]) -> bool | None:
        """One VO result (ok, motion since the previous pair at capture time `t_s`).
        Returns the new state when it changes, else None. A failed or first result, or
        one out of order, only marks the time."""
        prev, self._t = self._t, t_s
        if not ok or prev is None or t_s <= prev or len(rotation) != 9:
            return None
        dt = t_s - prev
        speed = math.sqrt(sum(v * v for v in translation)) / dt
        turn = rotation_deg(rotation) / dt
        c = self.cfg
        if speed >= c.moving_m_s or turn >= c.moving_deg_s:
            self._fast += 1
            self._slow_since = None
            if not self.moving and self._fast >= c.moving_n:
                self.moving = True
                return True
            return None
        self._fast = 0
        if speed < c.moving_m_s / 2 and turn < c.moving_deg_s / 2:
            if self._slow_since is None:
                self._slow_since = t_s
            if self.moving and t_s - self._slow_since >= c.still_s:
                self.moving = False
                return False
        else:
            self._slow_since = None  # between the thresholds: neither
        return None


class HintPacer:
    """When the normalizer says its word: at once on a change, and every HINT_INTERVAL_S
    while tracks are alive or the rig moves (the gate's track TTL and a restarted broker
    both need hearing it again)."""

    def __init__(self, interval_s: float = HINT_INTERVAL_S) -> None:
        self.interval_s = interval_s
        self._said: tuple[bool, bool] | None = None
        self._at = 0.0

    def due(self, tracks: int, rig_moving: bool, now: float) -> bool:
        """Whether to send (tracks alive, rig moving) now; a True is taken as sent."""
        state = (tracks > 0, rig_moving)
        repeat = any(state) and now - self._at >= self.interval_s
        if state != self._said or repeat:
            self._said, self._at = state, now
            return True
        return False

    def forget(self) -> None:
        """The link went away: a new broker knows nothing; say it all again."""
        self._said = None
