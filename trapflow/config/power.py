"""Energy and the motion gate: the board's power model and what withholds pairs from the
recognisers while nothing moves."""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from trapflow.config.base import Section as _Section


class EnergyConfig(_Section):
    """The power model ledger.json's energy estimate uses (trapflow.power.energy.BOARDS)."""

    board: Literal["pi5", "orin_nano"] = "pi5"
    """Board whose power model turns CPU time into watts."""
    cameras: Annotated[int, msgspec.Meta(ge=0, le=8)] = 2
    """Cameras streaming."""
    battery_wh: Annotated[float, msgspec.Meta(ge=0)] = 0.0
    """Battery capacity; with it, the estimate says how many days it lasts (0: not said)."""
    usable: Annotated[float, msgspec.Meta(gt=0, le=1)] = 0.8
    """Share of the battery that may be drawn."""


class MotionGateConfig(_Section):
    """The motion gate's rules for every pool with `gate: motion` (docs/gate-and-energy.md)."""

    pre_roll: Annotated[int, msgspec.Meta(ge=0, le=100)] = 5
    """Withheld pairs kept in the frame ring and fed in order when motion begins; a
    `latest` pool takes none (it would keep only the newest of them), a fifo:N pool at most
    N - 1 (they are queued at once, with the pair that moved)."""
    keepalive_s: Annotated[float, msgspec.Meta(gt=0, le=86400)] = 5.0
    """One pair at least this often without motion: a still animal in view is still seen."""
    hold_s: Annotated[float, msgspec.Meta(ge=0, le=3600)] = 3.0
    """Pairs keep going for this long after the last motion (an animal pausing mid-walk)."""
    min_score: Annotated[float, msgspec.Meta(ge=0, lt=1)] = 0.0
    """Motion counts only with at least this score (share of the small image moving)."""
    busy_rate_hz: Annotated[float, msgspec.Meta(ge=0, le=240)] = 3.0
    """While the gate is open (motion, hold, a live track), at most this many pairs per
    second of capture time to each gated pool (0: every pair); the first pair of a motion
    onset and its pre-roll always go, the rest are counted `gated`. Tracks and counts keep
    (the tracker bridges the gaps); a length gets fewer views (docs/gate-and-energy.md)."""
    rig_moving_m_s: Annotated[float, msgspec.Meta(gt=0, le=100)] = 0.05
    """Visual odometry's speed from which the rig moves: the gate is off (every pair fed)
    until it is still again (docs/gate-and-energy.md)."""
    rig_moving_deg_s: Annotated[float, msgspec.Meta(gt=0, le=3600)] = 3.0
    """VO's rotation rate from which the rig moves."""
    rig_still_s: Annotated[float, msgspec.Meta(ge=0, le=3600)] = 2.0
    """Seconds below half of both before the rig is still and the gate on again."""
    idle_after_s: Annotated[float, msgspec.Meta(ge=0, le=86400)] = 0.0
    """Duty cycling, opt-in: seconds without motion before capture drops to idle_rate_hz
    (0: never). The first pair that moves brings the full rate back."""
    idle_rate_hz: Annotated[float, msgspec.Meta(gt=0, le=240)] = 2.0
    """Capture rate while idle (at most source.rate_hz): below VO's 10 pairs/s, a choice."""
