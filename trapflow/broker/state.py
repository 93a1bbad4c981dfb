"""The broker's decisions, pure: events in (pair arrived, worker ready, job done, tick),
actions out (dispatch, release). No sockets, no clocks: callers pass `now` in seconds.

Every pair that reaches a pool ends in exactly one counter (the loss ledger): processed,
failed (by kind), dropped (by the pool's policy), stale (it waited longer than the pool's
max_pending_age_s), inactive (the pool was deactivated, `trapflow pool NAME --deactivate`),
throttled (the degradation ladder gives the pool at most one pair per minimum interval),
timed out (its worker held it too long), lost (its worker died, or the run ended first) or,
in a pool with `gate: motion`, gated: the motion gate (trapflow.gate.policy) withheld it.
Ungated pools take every pair as they always did; a gated pool takes what the gate feeds it
(older pre-roll pairs first, in order) and holds a pair the gate keeps as pre-roll until it
is fed or gated.

A worker that leaves on purpose to be recycled (worker_gone with requeue) answered its last
pair first; what was dispatched to it after that answer it never started, so those pairs go
back to the front of the queue instead of being lost.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import msgspec

from trapflow.broker.policy import Pending
from trapflow.config.schema import Policy, parse_policy
from trapflow.errors import unreachable
from trapflow.gate import policy as gate
from trapflow.wire.messages import PoolStats
from trapflow.wire.pool_counters import SUMMED

# A worker that has said nothing for this long while idle is presumed dead.
IDLE_LIVENESS_S = 5.0
# Distinct failure kinds counted per pool; the rest are counted as "other".
MAX_FAILURE_KINDS = 16
# Weight of the newest pair in a pool's latency (an exponential moving average).
LATENCY_WEIGHT = 0.2
# Pairs of evicted workers whose late answer is still taken (per worker, oldest forgotten).
MAX_LATE_PER_WORKER = 64
MAX_LATE_WORKERS = 256

# Why an answer (Done or Failed) was refused: counted per reason, never applied.
REJECT_UNKNOWN_POOL = "unknown_pool"
REJECT_UNKNOWN_WORKER = "unknown_worker"
REJECT_NOT_DISPATCHED = "not_dispatched"
# A Done for a pair its worker holds whose result names another pair or pool: a worker must
# not attach any result to a pair it was given (issue 26 item 4).
REJECT_RESULT_SEQ = "result_seq"
REJECT_RESULT_POOL = "result_pool"


@dataclass(frozen=True)
class Dispatch:
    """Send pair `seq` to `worker`; gap = pairs this pool skipped since its last dispatch."""

    worker: bytes
    pool: str
    seq: int
    gap: int


@dataclass(frozen=True)
class Release:
    """No pool holds `seq` any more: its buffers can go."""

    seq: int


@dataclass(frozen=True)
class Evicted:
    """A worker was forgotten; `lost` are the pairs it held."""

    worker: bytes
    pool: str
    lost: tuple[int, ...]
    reason: str


@dataclass(frozen=True)
class Rejected:
    """An answer for a (worker, seq) that was never dispatched to that worker, or was
    answered already, or a Done whose result names another pair or pool: forged or confused.
    Nothing of it is applied; its result is dropped (a pair it held ends as timed out)."""

    worker: bytes
    pool: str
    seq: int
    reason: str
    named: tuple[int, str] | None = None  # (seq, pool) the result named, for result_* reasons


@dataclass(frozen=True)
class GateNotice:
    """The motion gate changed how it works (the rig moves, or is still again): one INFO line."""

    text: str


Action = Dispatch | Release | Evicted | Rejected | GateNotice


@dataclass(frozen=True)
class PoolSpec:
    """What the state machine needs to know about a pool."""

    policy: Policy
    timeout_s: float
    max_pending_age_s: float = 0.0  # 0: pending pairs never go stale
    max_detections: int = 256  # a result's most detections; the rest are cut and counted


@dataclass
class _Worker:
    ident: bytes
    pool: str
    credit: int = 0
    in_flight: dict[int, float] = field(default_factory=dict)  # seq -> dispatch time
    last_seen: float = 0.0


@dataclass
class _Pool:
    name: str
    spec: PoolSpec
    pending: Pending
    workers: dict[bytes, _Worker] = field(default_factory=dict)
    last_seq: int = -1  # last seq dispatched (ordered pools report gaps from it)
    # The counts since the broker started (pool_counters.SUMMED; a unit test holds them so)
    received: int = 0
    dispatched: int = 0
    dropped: int = 0
    processed: int = 0
    errors: int = 0
    timed_out: int = 0
    lost: int = 0
    inactive: int = 0
    throttled: int = 0
    stale: int = 0
    gated: int = 0  # withheld by the motion gate
    cut: int = 0  # detections cut from its results (boxes, not pairs)
    active: bool = True
    min_interval_s: float = 0.0  # at most one dispatch per interval (0: no limit)
    next_at: float = 0.0  # earliest next dispatch under min_interval_s
    latency_s: float | None = None  # pair arrival to answer, moving average
    failures: dict[str, int] = field(default_factory=dict)
    rr: int = 0


class BrokerState:
    """Pending buffers, worker credits and pair reference counts for every pool, and the
    motion gate of the gated ones (`gates`: pool -> its rules; pools not named take all)."""

    def __init__(self, pools: Mapping[str, PoolSpec], idle_liveness_s: float = IDLE_LIVENESS_S,
                 gates: Mapping[str, gate.GateConfig] | None = None, paced: bool = False):
        # paced: the source waits for the pools (a replay at rate 0) instead of outrunning
        # them; the broker then takes a pair only while holds_source() is false.
        self.paced = paced
        self._pools = {n: _Pool(n, s, Pending(s.policy)) for n, s in pools.items()}
        gated = {n: g for n, g in (gates or {}).items() if n in self._pools}
        self._gate = gate.GateState(gated) if gated else None
        self._holders: dict[int, int] = {}  # seq -> number of pools holding it
        self._arrived: dict[int, float] = {}  # seq -> when it reached the broker
        self._idle_liveness = idle_liveness_s
        # Evicted worker -> the pairs it held: its late answer is genuine (counted as late).
        self._late: dict[bytes, dict[int, str]] = {}
        self.rejected: dict[str, int] = {}
        self.late = 0
        self.pairs_in = 0

    # --- events -------------------------------------------------------------------

    def pair_arrived(self, seq: int, now: float, motion: bool | None = None,
                     score: float = 0.0, captured: float | None = None) -> list[Action]:
        """A new pair from capture: queue it in every ungated pool, let the gate say what
        the gated ones get (motion: what capture's gate saw; None, no result, is taken as
        motion: a gate that cannot see never withholds; captured: its capture time in s,
        which paces the gate's busy rate), dispatch what can go."""
        self.pairs_in += 1
        actions: list[Action] = []
        if not self._pools:
            return [Release(seq)]
        self._holders[seq] = len(self._pools)
        self._arrived[seq] = now
        for pool in self._pools.values():
            pool.received += 1
            if self._gate is None or not self._gate.gates(pool.name):
                actions.extend(self._enqueue(pool, seq, now, now))
        if self._gate is not None:
            seen = self._gate.pair(seq, True if motion is None else motion, score, now,
                                   captured)
            actions.extend(self._apply_gate(seen, now))
        return actions

    def gate_hint(self, tracks: int, rig_moving: bool, now: float) -> list[Action]:
        """The normalizer's word: `tracks` alive now (they hold the gated pools open, said
        again while they live) and whether visual odometry says the rig moves (the gate is
        off while it does: every pair fed). Nothing without a gated pool."""
        if self._gate is None:
            return []
        decided = self._gate.tracks_alive(tracks, now)
        decided += self._gate.set_rig_moving(rig_moving, now)
        return self._apply_gate(decided, now)

    def worker_ready(self, ident: bytes, pool_name: str, credit: int, now: float) -> list[Action]:
        """A worker announces `credit` more free slots."""
        pool = self._pools.get(pool_name)
        if pool is None or credit < 1:
            return []
        w = pool.workers.setdefault(ident, _Worker(ident, pool_name))
        w.credit += credit
        w.last_seen = now
        return self._dispatch(pool, now)

    def worker_seen(self, ident: bytes, pool_name: str, free: int, now: float) -> list[Action]:
        """A heartbeat. An unknown worker (evicted while alive) rejoins with its free slots."""
        pool = self._pools.get(pool_name)
        if pool is None:
            return []
        w = pool.workers.get(ident)
        if w is not None:
            w.last_seen = now
            return []
        return self.worker_ready(ident, pool_name, free, now) if free > 0 else []

    def job_done(
        self, ident: bytes, pool_name: str, seq: int, ok: bool, now: float, kind: str = "error",
        named: tuple[int, str] | None = None,
    ) -> list[Action]:
        """A worker finished (ok) or failed (with a kind) a pair; one credit comes back.
        `named`: the (seq, pool) that a Done's result says it answers.

        Only an answer for a pair dispatched to this very worker and not answered yet is
        taken, and a Done only with a result for that pair and the worker's pool; anything
        else returns a single Rejected and changes nothing else. A worker evicted while it
        held the pair (timed out, presumed dead) may still answer it once: it rejoins with
        the credit, and the answer counts as late.
        """
        pool = self._pools.get(pool_name)
        if pool is None:
            return self._reject(ident, pool_name, seq, REJECT_UNKNOWN_POOL)
        w = pool.workers.get(ident)
        actions: list[Action] = []
        given = w is not None and seq in w.in_flight
        late = None if given else self._late.get(ident)
        if not given and (late is None or late.get(seq) != pool_name):
            reason = REJECT_UNKNOWN_WORKER if w is None else REJECT_NOT_DISPATCHED
            return self._reject(ident, pool_name, seq, reason)
        if named is not None and named != (seq, pool_name):
            # The Done is for a pair this worker holds (pool_name is its pool); the result
            # speaks of another pair or pool.
            reason = REJECT_RESULT_SEQ if named[0] != seq else REJECT_RESULT_POOL
            return self._reject(ident, pool_name, seq, reason, named)
        if late is not None:
            del late[seq]  # its pair was counted when it was evicted; now it is answered
            if not late:
                del self._late[ident]
            self.late += 1
            if w is None:  # evicted earlier; it is alive, so it rejoins
                w = pool.workers.setdefault(ident, _Worker(ident, pool_name))
        else:
            assert w is not None  # given
            del w.in_flight[seq]
            arrived = self._arrived.get(seq)
            if arrived is not None:
                took = now - arrived
                pool.latency_s = took if pool.latency_s is None else \
                    pool.latency_s + LATENCY_WEIGHT * (took - pool.latency_s)
            if ok:
                pool.processed += 1
            else:
                pool.errors += 1
                # Bounded: a plugin inventing new kinds cannot grow the stats without limit.
                if kind in pool.failures or len(pool.failures) < MAX_FAILURE_KINDS:
                    pool.failures[kind] = pool.failures.get(kind, 0) + 1
                else:
                    pool.failures["other"] = pool.failures.get("other", 0) + 1
            actions.extend(self._unhold(seq))
        w.credit += 1
        w.last_seen = now
        actions.extend(self._dispatch(pool, now))
        return actions

    def detections_cut(self, pool_name: str, n: int) -> None:
        """An accepted result of this pool brought n detections over its max_detections."""
        self._known(pool_name).cut += n

    def tick(self, now: float) -> list[Action]:
        """Evict workers whose job timed out or who went silent while idle; drop pending
        pairs older than their pool's max_pending_age_s (counted as stale); tick the gate."""
        actions = self._apply_gate(self._gate.tick(now), now) if self._gate else []
        for pool in self._pools.values():
            max_age = pool.spec.max_pending_age_s
            if max_age > 0:
                for seq in pool.pending.expire(now - max_age):
                    pool.stale += 1
                    actions.extend(self._unhold(seq))
            for w in list(pool.workers.values()):
                if w.in_flight and now - min(w.in_flight.values()) > pool.spec.timeout_s:
                    reason = f"job older than timeout_s={pool.spec.timeout_s:g}"
                    actions.extend(self._evict(pool, w, reason, timed_out=True, late=True))
                elif not w.in_flight and now - w.last_seen > self._idle_liveness:
                    reason = f"silent for more than {self._idle_liveness:g} s"
                    actions.extend(self._evict(pool, w, reason, late=True))
        return actions

    def worker_gone(self, ident: bytes, reason: str, now: float,
                    requeue: bool = False) -> list[Action]:
        """The supervisor saw this worker exit, or the worker said goodbye: forget it now
        rather than at timeout. With `requeue` (a recycled worker, which answered its last
        pair before leaving) the pairs it still held were never started: they are queued
        again, at the front, under the pool's policy, instead of being lost."""
        for pool in self._pools.values():
            w = pool.workers.get(ident)
            if w is not None:
                if not requeue:
                    return self._evict(pool, w, reason) + self._dispatch(pool, now)
                held = [(seq, self._arrived.get(seq, t)) for seq, t in sorted(w.in_flight.items())]
                w.in_flight.clear()
                actions = self._evict(pool, w, reason)
                if not pool.active:  # deactivated meanwhile: nothing of it is queued now
                    for seq, _ in held:
                        pool.inactive += 1
                        actions.extend(self._unhold(seq))
                    return actions
                for seq in pool.pending.requeue(held):
                    pool.dropped += 1
                    actions.extend(self._unhold(seq))
                return actions + self._dispatch(pool, now)
        return []

    def set_active(self, pool_name: str, active: bool, now: float) -> list[Action]:
        """Deactivate a pool (what it holds pending is dropped as inactive; pairs in flight
        finish) or activate it again. ValueError for a pool this broker does not have."""
        pool = self._known(pool_name)
        pool.active = active
        actions: list[Action] = []
        if not active:
            for seq, _ in pool.pending.clear():
                pool.inactive += 1
                actions.extend(self._unhold(seq))
        return actions

    def set_interval(self, pool_name: str, min_interval_s: float, now: float
                     ) -> list[Action]:
        """At most one pair dispatched per `min_interval_s` (0: no limit), as the
        degradation ladder asks: pairs that arrive before the next one is due, and those
        left pending when one goes, are counted throttled. ValueError for an unknown pool
        or a negative interval."""
        pool = self._known(pool_name)
        if not min_interval_s >= 0:
            raise ValueError(f"pool {pool_name!r}: expected a minimum interval >= 0 s, got "
                             f"{min_interval_s}")
        pool.min_interval_s = min_interval_s
        pool.next_at = min(pool.next_at, now + min_interval_s) if min_interval_s else 0.0
        return self._dispatch(pool, now)

    def set_policy(self, pool_name: str, policy: str, now: float) -> list[Action]:
        """A new policy: what is pending is queued again under it (its drops counted).
        ValueError for an unknown pool or a policy that does not parse."""
        pool = self._known(pool_name)
        parsed = parse_policy(policy)
        pool.spec = PoolSpec(parsed, pool.spec.timeout_s, pool.spec.max_pending_age_s)
        old, pool.pending = pool.pending.clear(), Pending(parsed)
        actions: list[Action] = []
        for seq, born in old:
            for dropped in pool.pending.push(seq, born):
                pool.dropped += 1
                actions.extend(self._unhold(dropped))
        return actions + self._dispatch(pool, now)

    def pool_switch(self, pool_name: str, active: bool | None, policy: str | None,
                    min_interval_s: float | None, now: float) -> tuple[list[Action], list[str]]:
        """A runtime switch of a pool (trapflow pool, the ladder): its actions and what
        changed, for the log. Checked whole first: a ValueError changes nothing."""
        self._known(pool_name)
        if policy is not None:
            parse_policy(policy)
        if min_interval_s is not None and not min_interval_s >= 0:
            raise ValueError(f"pool {pool_name!r}: expected a minimum interval >= 0 s, got "
                             f"{min_interval_s}")
        actions: list[Action] = []
        done: list[str] = []
        if active is not None:
            actions += self.set_active(pool_name, active, now)
            done.append("active" if active else "inactive")
        if policy is not None:
            actions += self.set_policy(pool_name, policy, now)
            done.append(f"policy {policy}")
        if min_interval_s is not None:
            actions += self.set_interval(pool_name, min_interval_s, now)
            done.append(f"minimum interval {min_interval_s:g} s")
        return actions, done

    def finish(self) -> list[Action]:
        """The run ends: what the gate kept as pre-roll is gated, what is pending or in
        flight is lost; every pair is accounted for."""
        actions = self._apply_gate(self._gate.finish(), 0.0) if self._gate else []
        for pool in self._pools.values():
            for seq, _ in pool.pending.clear():
                pool.lost += 1
                actions.extend(self._unhold(seq))
            for w in list(pool.workers.values()):
                actions.extend(self._evict(pool, w, "run ended"))
        return actions

    # --- queries ------------------------------------------------------------------

    def pool_workers(self, pool_name: str) -> list[bytes]:
        """The workers this pool knows now (ValueError for an unknown pool)."""
        return list(self._known(pool_name).workers)

    def held(self) -> int:
        """Pairs still referenced by some pool (pending or in flight)."""
        return len(self._holders)

    def pool_stats(self) -> dict[str, PoolStats]:
        """Counters of every pool."""
        kept = {n: c.kept for n, c in self._gate.counts().items()} if self._gate else {}
        return {
            p.name: msgspec.structs.replace(PoolStats(
                workers=len(p.workers),
                in_flight=sum(len(w.in_flight) for w in p.workers.values()),
                pending=len(p.pending),
                kept=kept.get(p.name, 0),
                failures=dict(p.failures),
                active=p.active,
                min_interval_s=p.min_interval_s,
                latency_ms=round(p.latency_s * 1000, 1) if p.latency_s is not None else 0.0,
            ), **{name: getattr(p, name) for name in SUMMED})
            for p in self._pools.values()
        }

    def gate_time(self) -> tuple[float, float]:
        """Seconds the motion gate was open (active) and idle; (0, 0) without a gated pool."""
        return (self._gate.active_s, self._gate.idle_s) if self._gate else (0.0, 0.0)

    def worker_pools(self) -> dict[bytes, str]:
        """Every worker the state knows (live), and its pool."""
        return {w: p.name for p in self._pools.values() for w in p.workers}

    def has_room(self) -> bool:
        """Whether a new pair would be queued without a drop in every pool that has workers
        and takes pairs as they come (active, unthrottled): what capture of a finite source
        read at full speed waits for (back-pressure to the source). A pool with no worker
        does not hold the source back: nobody may ever come to empty it. A gated pool holds
        it like any other (a replay with --gate under load dropped 2 of the pairs the gate
        let through to a `latest` pool: the source had outrun it); while the gate withholds
        its pairs nothing waits in it, so it holds nothing back."""
        for pool in self._pools.values():
            if not pool.active or pool.min_interval_s or not pool.workers:
                continue
            if len(pool.pending) >= pool.spec.policy.bound:
                return False
        return True

    def holds_source(self) -> bool:
        """Whether capture must wait: paced, and a pair taken now would make a pool drop one."""
        return self.paced and not self.has_room()

    def drained(self) -> bool:
        """Nothing pending or in flight anywhere."""
        return not self._holders

    # --- internals ----------------------------------------------------------------

    def _known(self, name: str) -> _Pool:
        pool = self._pools.get(name)
        if pool is None:
            raise ValueError(f"no pool {name!r} in the broker (pools: "
                             f"{', '.join(sorted(self._pools)) or 'none'})")
        return pool

    def _reject(self, ident: bytes, pool: str, seq: int, reason: str,
                named: tuple[int, str] | None = None) -> list[Action]:
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        return [Rejected(ident, pool, seq, reason, named)]

    def _remember_late(self, ident: bytes, pool: str, lost: tuple[int, ...]) -> None:
        if not lost:
            return
        late = self._late.setdefault(ident, {})
        for seq in lost:
            late[seq] = pool
        while len(late) > MAX_LATE_PER_WORKER:
            del late[next(iter(late))]
        while len(self._late) > MAX_LATE_WORKERS:
            del self._late[next(iter(self._late))]

    def _unhold(self, seq: int) -> list[Action]:
        n = self._holders.get(seq, 0) - 1
        if n > 0:
            self._holders[seq] = n
            return []
        self._holders.pop(seq, None)
        self._arrived.pop(seq, None)
        return [Release(seq)]

    def _enqueue(self, pool: _Pool, seq: int, born: float, now: float) -> list[Action]:
        """Queue a pair (arrived at `born`) in one pool under its state and policy."""
        if not pool.active:
            pool.inactive += 1
            return self._unhold(seq)
        if pool.min_interval_s and now < pool.next_at:
            pool.throttled += 1  # the level's doing, not the policy's
            return self._unhold(seq)
        actions: list[Action] = []
        for old in pool.pending.push(seq, born):
            pool.dropped += 1
            actions.extend(self._unhold(old))
        return actions + self._dispatch(pool, now)

    def _apply_gate(self, decided: list[gate.Action], now: float) -> list[Action]:
        """The gate's actions: Feed queues the pair, Keep holds it on, Gated lets it go, a
        Notice is said."""
        actions: list[Action] = []
        for a in decided:
            if isinstance(a, gate.Feed):
                pool = self._pools[a.pool]
                actions.extend(self._enqueue(pool, a.seq, self._arrived.get(a.seq, now), now))
            elif isinstance(a, gate.Keep):
                pass  # the pool's hold on the pair stays: its slot stays in the ring
            elif isinstance(a, gate.Gated):
                self._pools[a.pool].gated += 1
                actions.extend(self._unhold(a.seq))
            elif isinstance(a, gate.Notice):
                actions.append(GateNotice(a.text))
            else:
                unreachable(a)
        return actions

    def _pick(self, pool: _Pool) -> _Worker | None:
        ready = [w for w in pool.workers.values() if w.credit > 0]
        if not ready:
            return None
        # Least loaded first; round robin among equals so a pool shares work evenly.
        pool.rr += 1
        least = min(len(w.in_flight) for w in ready)
        ties = [w for w in ready if len(w.in_flight) == least]
        return ties[pool.rr % len(ties)]

    def _dispatch(self, pool: _Pool, now: float) -> list[Action]:
        actions: list[Action] = []
        while len(pool.pending):
            if pool.min_interval_s and now < pool.next_at:
                break
            w = self._pick(pool)
            if w is None:
                break
            seq = pool.pending.pop()
            assert seq is not None
            gap = seq - pool.last_seq - 1 if pool.last_seq >= 0 else 0
            pool.last_seq = seq
            w.credit -= 1
            w.in_flight[seq] = now
            pool.dispatched += 1
            actions.append(Dispatch(w.ident, pool.name, seq, max(gap, 0)))
            if pool.min_interval_s:
                # One pair per interval: the rest waiting now would be due only later,
                # older than what will have arrived by then.
                pool.next_at = now + pool.min_interval_s
                for old, _born in pool.pending.clear():
                    pool.throttled += 1
                    actions.extend(self._unhold(old))
        return actions

    def _evict(self, pool: _Pool, w: _Worker, reason: str,
               timed_out: bool = False, late: bool = False) -> list[Action]:
        """Forget a worker; late: it may be alive (slow or silent) and answer afterwards."""
        del pool.workers[w.ident]
        lost = tuple(sorted(w.in_flight))
        if late:
            self._remember_late(w.ident, pool.name, lost)
        if timed_out:
            pool.timed_out += len(lost)
        else:
            pool.lost += len(lost)
        actions: list[Action] = [Evicted(w.ident, pool.name, lost, reason)]
        for seq in lost:
            actions.extend(self._unhold(seq))
        return actions
