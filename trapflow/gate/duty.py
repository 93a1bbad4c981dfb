"""Duty cycling of capture, pure: after a while without motion capture drops to an idle
rate, and the first pair that changes brings the full rate back. Capture runs it on its own
motion results (no round trip: the full rate is back for the very next pair). Opt-in."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class DutyConfig:
    """An idle rate after a while without motion; off unless idle_after_s > 0."""

    idle_after_s: float = 0.0
    """Seconds without motion before the idle rate; 0: never."""
    idle_rate_hz: float = 2.0
    """Capture rate while idle (never above the full rate)."""

    def __post_init__(self) -> None:
        if not self.idle_after_s >= 0:
            raise ValueError(f"gate idle_after_s: expected >= 0 s, got {self.idle_after_s}")
        if not 0 < self.idle_rate_hz <= 240:
            raise ValueError(f"gate idle_rate_hz: expected 0 < rate <= 240, "
                             f"got {self.idle_rate_hz}")


class DutyCycle:
    """Capture's rate now: `full_hz`, or the idle rate after idle_after_s without change."""

    def __init__(self, cfg: DutyConfig, full_hz: float) -> None:
        self.cfg = cfg
        self.full_hz = full_hz
        # Idle never raises the rate: a source slower than the idle rate keeps its own.
        self.idle_hz = min(cfg.idle_rate_hz, full_hz)
        self.idle = False
        self._changed: float | None = None  # when a pair last changed (the start counts)

    @property
    def enabled(self) -> bool:
        """Whether the rate ever changes."""
        return self.cfg.idle_after_s > 0 and self.idle_hz < self.full_hz

    @property
    def hz(self) -> float:
        """The rate now."""
        return self.idle_hz if self.idle else self.full_hz

    def pair(self, changed: bool, now: float) -> float | None:
        """One pair's motion result (`changed`: motion, or a new scene the detector learnt
        afresh: a light change or a moving rig, after which VO wants every pair). Returns
        the new rate when it changes, else None."""
        if not self.enabled:
            return None
        if self._changed is None or changed:
            self._changed = now
        if changed and self.idle:
            self.idle = False
            return self.full_hz
        if not self.idle and now - self._changed >= self.cfg.idle_after_s:
            self.idle = True
            return self.idle_hz
        return None
