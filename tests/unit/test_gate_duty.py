"""Capture's duty cycling, pure: when it drops to the idle rate and when the full rate is
back, for the very next pair."""

from __future__ import annotations

import pytest

from trapflow.gate.duty import DutyConfig, DutyCycle

HZ = 10.0


def play(duty: DutyCycle, changed: list[bool]) -> list[tuple[int, float]]:
    """Pairs 0.. at the rate in force when each came; returns (pair, new rate) changes."""
    out: list[tuple[int, float]] = []
    now = 0.0
    for seq, moved in enumerate(changed):
        hz = duty.pair(moved, now)
        if hz is not None:
            out.append((seq, hz))
        now = round(now + 1.0 / duty.hz, 9)  # exact tenths: the table counts pairs
    return out


F, T = False, True


@pytest.mark.parametrize(("cfg", "full_hz", "changed", "want"), [
    # Off by default: never a rate change.
    (DutyConfig(), HZ, [F] * 200, []),
    # Idle rate after 5 s without motion (the start counts as motion): pair 50 at t = 5 s.
    (DutyConfig(idle_after_s=5.0), HZ, [F] * 60, [(50, 2.0)]),
    # The first pair that changes brings the full rate back on that very pair, and the idle
    # rate comes again 5 s after it (50 pairs at 10 Hz).
    (DutyConfig(idle_after_s=5.0), HZ, [F] * 55 + [T] + [F] * 60, [(50, 2.0), (55, HZ),
                                                                   (105, 2.0)]),
    # Motion now and then keeps the full rate.
    (DutyConfig(idle_after_s=5.0), HZ, ([F] * 40 + [T]) * 4, []),
    # An idle rate at or above the full rate is no duty cycling: the rate never rises.
    (DutyConfig(idle_after_s=1.0, idle_rate_hz=20.0), HZ, [F] * 60, []),
    (DutyConfig(idle_after_s=1.0, idle_rate_hz=2.0), 2.0, [F] * 60, []),
])
def test_rate_changes(cfg: DutyConfig, full_hz: float, changed: list[bool],
                      want: list[tuple[int, float]]) -> None:
    assert play(DutyCycle(cfg, full_hz), changed) == want


def test_idle_rate_never_above_the_full_rate() -> None:
    """A degraded source (or a slow one) never gets a faster idle rate than its own."""
    duty = DutyCycle(DutyConfig(idle_after_s=1.0, idle_rate_hz=8.0), 5.0)
    assert duty.idle_hz == 5.0 and not duty.enabled


@pytest.mark.parametrize(("kwargs", "error"), [
    ({"idle_after_s": -1.0}, "idle_after_s: expected >= 0 s, got -1.0"),  # negative
    ({"idle_rate_hz": 0.0}, "idle_rate_hz: expected 0 < rate <= 240, got 0.0"),  # stops
])
def test_config_rejects(kwargs: dict[str, float], error: str) -> None:
    with pytest.raises(ValueError, match=error):
        DutyConfig(**kwargs)
