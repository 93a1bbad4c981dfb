"""The gate's decisions, pure: events in (pair seen with its motion result, tracks alive,
rig moving, tick), actions out (feed, keep for pre-roll, gated, notice).
No sockets, no clocks: callers pass `now` in seconds (monotonic).

Per gated pool a pair is fed when it moved, while the hold lasts after motion (hold_s), while
any track is alive, or as the keep-alive (one pair every keepalive_s); otherwise it is kept
as pre-roll (the last `pre_roll` withheld pairs, fed in order when motion begins) and, once
older pairs push it out, gated for good. While the gate is open (motion, hold, track) a pool
gets at most busy_rate_hz pairs per second of capture time, the first pair of a motion
onset and its pre-roll always; the rest are gated. Every pair of a pool ends in exactly one
Feed or one Gated. A moving rig turns the gate off (everything fed) until it is still again.
Capture's rate (duty cycling) is trapflow.gate.duty's to decide, in the capture process.
"""

from __future__ import annotations

import enum
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field

from trapflow.config.schema import Config, Policy
from trapflow.gate.duty import DutyConfig
from trapflow.gate.hint import RigConfig

# A track not said alive again for this long is taken as ended (its end was lost).
TRACK_TTL_S = 10.0
# The id under which tracks_alive() holds the gate: the normalizer's count of live tracks.
TRACKS_ALIVE = -1
# Longest interval between two pairs counted as active or idle time (a stalled source's gap
# is neither).
MAX_PAIR_GAP_S = 2.0


class Reason(enum.Enum):
    """Why a pair was fed to a gated pool."""

    MOTION = "motion"
    PRE_ROLL = "pre_roll"
    HOLD = "hold"
    TRACK = "track"
    KEEPALIVE = "keepalive"
    OFF = "off"  # the gate is off: the rig moves


@dataclass(frozen=True)
class GateConfig:
    """One gated pool's rules."""

    pre_roll: int = 5
    """Withheld pairs kept (in the frame ring) and fed in order when motion begins: 0.5 s
    at 10 pairs/s, what an animal crossing the frame edge needs before it is seen moving."""
    keepalive_s: float = 5.0
    """One pair at least this often without motion: a still animal in view is still seen."""
    hold_s: float = 3.0
    """Pairs keep going for this long after the last motion (an animal pausing mid-walk)."""
    min_score: float = 0.0
    """A motion result counts only with at least this score (share of the image moving)."""
    busy_rate_hz: float = 0.0
    """While the gate is open, at most this many pairs per second of capture time (0: every
    pair): the tracker associates by capture time, so a detector seeing one pair in three
    keeps its tracks, and a busy scene costs a third of the pairs."""

    def __post_init__(self) -> None:
        if not 0 <= self.pre_roll <= 100:
            raise ValueError(f"gate pre_roll: expected 0..100 pairs, got {self.pre_roll}")
        if not self.keepalive_s > 0:
            raise ValueError(f"gate keepalive_s: expected > 0 s, got {self.keepalive_s}")
        if not self.hold_s >= 0:
            raise ValueError(f"gate hold_s: expected >= 0 s, got {self.hold_s}")
        if not 0 <= self.min_score < 1:
            raise ValueError(f"gate min_score: expected 0 <= score < 1, got {self.min_score}")
        if not self.busy_rate_hz >= 0:
            raise ValueError(f"gate busy_rate_hz: expected >= 0 pairs/s, got {self.busy_rate_hz}")


def gated_pools(cfg: Config) -> dict[str, GateConfig]:
    """Every pool with `gate: motion` and its rules, from the config's `gate` section. The
    pre-roll is queued at once with the pair that moved, so a pool takes only what its
    queue holds beside it: a `latest` pool none (the rest would only be counted dropped,
    holding ring slots meanwhile), a fifo:N pool at most N - 1."""
    g = cfg.gate
    return {name: GateConfig(pre_roll=_pre_roll(p.parsed_policy, g.pre_roll),
                             keepalive_s=g.keepalive_s, hold_s=g.hold_s, min_score=g.min_score,
                             busy_rate_hz=g.busy_rate_hz)
            for name, p in cfg.pools.items() if p.gate == "motion"}


def _pre_roll(policy: Policy, pre_roll: int) -> int:
    if policy.kind == "latest":
        return 0
    if policy.kind == "fifo":
        return min(pre_roll, policy.bound - 1)
    return pre_roll


@dataclass(frozen=True)
class Feed:
    """Give pair `seq` to `pool` (queue it under the pool's policy)."""

    pool: str
    seq: int
    reason: Reason


@dataclass(frozen=True)
class Keep:
    """Withhold pair `seq` from `pool` for now, but keep it: it may be fed as pre-roll."""

    pool: str
    seq: int


@dataclass(frozen=True)
class Gated:
    """`pool` will never get pair `seq`: count it gated and drop the pool's hold on it."""

    pool: str
    seq: int


@dataclass(frozen=True)
class Notice:
    """One INFO line for the log: the gate changed how it works."""

    text: str


Action = Feed | Keep | Gated | Notice


@dataclass(frozen=True)
class GateCounts:
    """One gated pool's counters: pairs fed by reason, gated, kept for pre-roll now."""

    fed: dict[str, int]
    gated: int
    kept: int


@dataclass
class _Pool:
    name: str
    cfg: GateConfig
    kept: deque[int] = field(default_factory=deque)
    last_fed: float | None = None
    fed_at: float | None = None  # capture time of the last pair fed while open
    due: float | None = None  # capture time from which the busy rate lets the next one go
    last_motion: float | None = None
    fed: dict[Reason, int] = field(default_factory=dict)
    gated: int = 0


class GateState:
    """Feed-or-withhold for every gated pool of one pipeline."""

    def __init__(self, pools: Mapping[str, GateConfig], track_ttl_s: float = TRACK_TTL_S
                 ) -> None:
        self._pools = {n: _Pool(n, c) for n, c in pools.items()}
        self._track_ttl = track_ttl_s
        self._tracks: dict[int, float] = {}  # track id -> when last said alive
        self.rig_moving = False
        # Seconds the gate was open (some gated pool fed for motion, pre-roll, hold, a track
        # or a moving rig) and idle (withheld, or only the keep-alive): the report's split.
        self.active_s = 0.0
        self.idle_s = 0.0
        self._last_pair: float | None = None

    # --- events -------------------------------------------------------------------

    def pair(self, seq: int, motion: bool, score: float, now: float,
             captured: float | None = None) -> list[Action]:
        """Pair `seq` was seen (motion result of its left image; `captured`, its capture time
        in seconds, paces busy_rate_hz: `now` when not given): a Feed, Keep or Gated per
        pool, pre-roll Feeds (older seqs, in order) before the Feed of a pair that moved."""
        actions: list[Action] = []
        tracking = self._tracking(now)
        at = now if captured is None else captured
        for pool in self._pools.values():
            actions.extend(self._decide(pool, seq, motion, score, tracking, now, at))
        if self._last_pair is not None and now > self._last_pair:
            gap = min(now - self._last_pair, MAX_PAIR_GAP_S)
            # Open: some pool fed for motion, hold, a track or a moving rig, or would have
            # but for its busy rate (a pair that moved holds its pool, see _decide).
            if self.rig_moving or tracking or any(self._held(p, now)
                                                  for p in self._pools.values()):
                self.active_s += gap
            else:
                self.idle_s += gap
        self._last_pair = now
        return actions

    def track_alive(self, track_id: int, now: float) -> list[Action]:
        """A recogniser's track is alive (say so again at least every track_ttl_s)."""
        self._tracks[track_id] = now
        return []

    def track_ended(self, track_id: int, now: float) -> list[Action]:
        """A track ended: the hold it gave ends with it (the pools' own hold_s still runs)."""
        self._tracks.pop(track_id, None)
        return []

    def tracks_alive(self, count: int, now: float) -> list[Action]:
        """The normalizer's word: `count` tracks are alive now (0: none). Said again at
        least every track_ttl_s while some are; its own tracks (track_alive) stay as they are."""
        if count > 0:
            return self.track_alive(TRACKS_ALIVE, now)
        return self.track_ended(TRACKS_ALIVE, now)

    def set_rig_moving(self, moving: bool, now: float) -> list[Action]:
        """Visual odometry says whether the rig moves. A moving rig changes every pixel, so
        the gate turns itself off (one Notice) and on again when the rig is still."""
        if moving == self.rig_moving:
            return []
        self.rig_moving = moving
        actions: list[Action] = []
        if moving:
            actions.append(Notice("motion gate off: the rig moves, every pair is fed"))
            for pool in self._pools.values():
                actions.extend(self._gate_kept(pool))
        else:
            # Capture's detector learns the background afresh by itself: a moving view
            # changes more than max_cover of the frame, which it takes as a new scene.
            actions.append(Notice("motion gate on: the rig is still"))
            for pool in self._pools.values():
                pool.last_motion = now  # hold while the new background is learnt
        return actions

    def tick(self, now: float) -> list[Action]:
        """Forget tracks not said alive for track_ttl_s."""
        for tid in [t for t, seen in self._tracks.items() if now - seen > self._track_ttl]:
            del self._tracks[tid]
        return []

    def finish(self) -> list[Action]:
        """The run ends: what is kept for pre-roll is gated."""
        actions: list[Action] = []
        for pool in self._pools.values():
            actions.extend(self._gate_kept(pool))
        return actions

    # --- queries ------------------------------------------------------------------

    def counts(self) -> dict[str, GateCounts]:
        """Counters of every gated pool."""
        return {p.name: GateCounts(fed={r.value: n for r, n in p.fed.items()}, gated=p.gated,
                                   kept=len(p.kept))
                for p in self._pools.values()}

    def gates(self, pool_name: str) -> bool:
        """Whether this gate decides what the pool gets."""
        return pool_name in self._pools

    def open(self, pool_name: str, now: float) -> bool:
        """Whether the pool would get a still pair now (hold, track or gate off)."""
        pool = self._pools[pool_name]
        return self.rig_moving or self._held(pool, now) or self._tracking(now)

    # --- internals ----------------------------------------------------------------

    def _decide(self, pool: _Pool, seq: int, motion: bool, score: float, tracking: bool,
                now: float, at: float) -> list[Action]:
        if self.rig_moving:
            return [self._feed(pool, seq, Reason.OFF, now)]
        was_open = self._held(pool, now) or tracking
        if motion and score >= pool.cfg.min_score:
            pool.last_motion = now
            if was_open and self._busy(pool, at, now):
                return [self._gate(pool, seq)]
            self._pace(pool, at, onset=not was_open)  # an onset always goes
            pre = [self._feed(pool, old, Reason.PRE_ROLL, now) for old in sorted(pool.kept)]
            pool.kept.clear()
            return [*pre, self._feed(pool, seq, Reason.MOTION, now)]
        if was_open:
            if self._busy(pool, at, now):
                return [self._gate(pool, seq)]
            self._pace(pool, at, onset=False)
            reason = Reason.HOLD if self._held(pool, now) else Reason.TRACK
            return [self._feed(pool, seq, reason, now)]
        if self._keepalive_due(pool, now):
            return [self._feed(pool, seq, Reason.KEEPALIVE, now)]
        if pool.cfg.pre_roll == 0:
            return [self._gate(pool, seq)]
        pool.kept.append(seq)
        actions: list[Action] = [Keep(pool.name, seq)]
        while len(pool.kept) > pool.cfg.pre_roll:
            pool.gated += 1
            actions.append(Gated(pool.name, pool.kept.popleft()))
        return actions

    def _feed(self, pool: _Pool, seq: int, reason: Reason, now: float) -> Feed:
        pool.last_fed = now
        pool.fed[reason] = pool.fed.get(reason, 0) + 1
        return Feed(pool.name, seq, reason)

    def _gate(self, pool: _Pool, seq: int) -> Gated:
        pool.gated += 1
        return Gated(pool.name, seq)

    def _busy(self, pool: _Pool, at: float, now: float) -> bool:
        """Whether the busy rate withholds a pair captured at `at` from an open gate (never
        past the keep-alive; a capture time that went back, a source looping or restarted,
        starts it afresh)."""
        if pool.cfg.busy_rate_hz == 0 or pool.fed_at is None or pool.due is None:
            return False
        if self._keepalive_due(pool, now):
            return False
        # Half a microsecond of slack: capture times in ns, a period of 1/3 s is not exact.
        return pool.fed_at <= at < pool.due - 5e-7

    def _pace(self, pool: _Pool, at: float, onset: bool) -> None:
        """A pair captured at `at` is fed while the gate is open: when the next may go. Due
        times step by the period, not from the pair fed, so 3 pairs/s of a 10 pairs/s
        capture is one pair in 3 or 4, not one in 4; a pair far past its due time (a gap,
        a restarted source) starts afresh instead of letting a burst through."""
        rate = pool.cfg.busy_rate_hz
        if rate == 0:
            return
        period = 1.0 / rate
        on_time = (not onset and pool.fed_at is not None and pool.due is not None
                   and pool.fed_at <= at < pool.due + period)
        pool.due = (pool.due + period) if on_time and pool.due is not None else at + period
        pool.fed_at = at

    def _keepalive_due(self, pool: _Pool, now: float) -> bool:
        return pool.last_fed is None or now - pool.last_fed >= pool.cfg.keepalive_s

    def _held(self, pool: _Pool, now: float) -> bool:
        return pool.last_motion is not None and now - pool.last_motion <= pool.cfg.hold_s

    def _tracking(self, now: float) -> bool:
        return any(now - seen <= self._track_ttl for seen in self._tracks.values())

    def _gate_kept(self, pool: _Pool) -> list[Action]:
        out: list[Action] = [Gated(pool.name, seq) for seq in pool.kept]
        pool.gated += len(pool.kept)
        pool.kept.clear()
        return out


def rig_config(cfg: Config) -> RigConfig:
    """When VO means the rig moves, from the config's `gate` section."""
    g = cfg.gate
    return RigConfig(moving_m_s=g.rig_moving_m_s, moving_deg_s=g.rig_moving_deg_s,
                     still_s=g.rig_still_s)


def duty_config(cfg: Config) -> DutyConfig:
    """Capture's duty cycling, from the config's `gate` section."""
    return DutyConfig(idle_after_s=cfg.gate.idle_after_s, idle_rate_hz=cfg.gate.idle_rate_hz)
