"""The supervisor's decisions, pure: events in (spawned, heartbeat, exit, tick, command),
actions out (spawn, kill, tell the broker a worker is gone, give up, retry, stop).
No processes, sockets or clocks: callers pass `now` in seconds (monotonic).

A worker that exits with a recycle status (EXIT_RECYCLED_RSS, EXIT_RECYCLED_JOBS) left on
purpose: it is replaced at once, outside the restart budget, and counted per pool and why.

Per node: its lifecycle state as last reported, liveness (silence longer than the node's
limit gets it killed: its pool's timeout_s for a worker that took work, the start-up
deadline while it is still configuring), a restart budget per window with doubling
back-off, and what happens when the budget is spent: an ordinary node is given up and
retried after a cool-down with a fresh budget; an essential node (broker, capture,
normalizer) is never abandoned while the supervisor lives, it keeps restarting at the
capped back-off. Every give-up and retry is kept in a timeline for status and the ledger.

Runtime control (`trapflow pool`, `trapflow param`) is decided here too: per pool its
lifecycle (active/inactive, moved as a ROS 2 lifecycle node moves: deactivate only from
active, activate only from inactive), its worker count, policy and parameters. A command
that cannot apply raises Refused (with what was expected and the fix); one that applies
returns actions (add or retire workers, tell the broker, restart the pool's workers with
new parameters) and one "control" entry in the timeline.

The degradation ladder (trapflow.ladder) is applied here: a level change deactivates the
pools the new level switches off, activates again those the ladder itself had switched off,
sets each pool's minimum interval between pairs, and leaves one "level" entry. The rule
with the operator: the ladder never activates a pool the operator deactivated (it stays
inactive whatever the level until the operator activates it; deactivating a pool the ladder
has off takes it over); a pool the operator activates while the ladder has it off runs
until the next level change.
"""

from __future__ import annotations

import enum
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from trapflow.ladder import Ladder, PoolLevel, Readings
from trapflow.policy import parse_policy

# Roles the pipeline cannot do without: never given up while the supervisor lives.
ESSENTIAL_ROLES = frozenset({"broker", "capture", "normalizer"})
# How long every node has to report its first state before start-up is declared failed.
STARTUP_TIMEOUT_S = 60.0
# Timeline entries kept for status and the ledger (the oldest go first).
MAX_TIMELINE = 1000
# Workers one pool may have (config's PoolConfig.count bound).
MAX_POOL_COUNT = 64
# Exit statuses of a worker recycled on purpose: past its pool's max_rss_mb, or done with
# its max_jobs. It answered its last pair and said goodbye to the broker; it is replaced at
# once, without back-off and outside the restart budget (sysexits' EX_TEMPFAIL and next).
EXIT_RECYCLED_RSS = 75
EXIT_RECYCLED_JOBS = 76
RECYCLE_EXITS = {EXIT_RECYCLED_RSS: "rss", EXIT_RECYCLED_JOBS: "jobs"}


class Lifecycle(str, enum.Enum):
    """ROS 2 lifecycle states, as nodes report them in heartbeats (a str: the wire form)."""

    UNCONFIGURED = "unconfigured"
    INACTIVE = "inactive"
    ACTIVE = "active"
    FINALIZED = "finalized"

    def __str__(self) -> str:
        return self.value

    @classmethod
    def parse(cls, text: str) -> Lifecycle | None:
        """The state named on the wire, or None for a name no node sends."""
        try:
            return cls(text)
        except ValueError:
            return None


@dataclass(frozen=True)
class Budget:
    """Restarts allowed per window, their back-off, and the cool-down after a give-up."""

    max_restarts: int = 5
    window_s: float = 60.0
    backoff_s: float = 0.5
    backoff_max_s: float = 10.0
    cooldown_s: float = 300.0


@dataclass(frozen=True)
class NodePlan:
    """What the core needs to know about one node: its name, role and liveness limit."""

    name: str
    role: str
    liveness_s: float
    startup_s: float = STARTUP_TIMEOUT_S
    pool: str = ""  # a worker's pool

    @property
    def essential(self) -> bool:
        return self.role in ESSENTIAL_ROLES


# --- actions ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Spawn:
    """Start the node's process; `restart` counts its restarts so far (0: the first);
    `recycled` says why a worker recycled on purpose is replaced (rss, jobs), else ""."""

    name: str
    restart: int
    recycled: str = ""


@dataclass(frozen=True)
class Kill:
    """Kill the node's process (SIGKILL): it is silent past its limit."""

    name: str
    reason: str


@dataclass(frozen=True)
class WorkerGone:
    """Tell the broker at once that this worker process died: its pairs are lost, unless
    it was `recycled` (rss, jobs): then what it held it never started, and is queued again."""

    name: str
    reason: str
    recycled: str = ""


@dataclass(frozen=True)
class GiveUp:
    """The node's restart budget is spent: no restart until `retry_at`."""

    name: str
    reason: str
    retry_at: float


@dataclass(frozen=True)
class Retry:
    """A given-up node's cool-down is over: it gets a fresh budget (a Spawn follows)."""

    name: str
    reason: str


@dataclass(frozen=True)
class Stop:
    """Stop the whole pipeline."""

    reason: str


@dataclass(frozen=True)
class AddWorker:
    """A pool grew: create worker `index` of `pool` (a Spawn of `name` follows)."""

    name: str
    pool: str
    index: int


@dataclass(frozen=True)
class Retire:
    """A pool shrank: stop this worker gracefully; it is not restarted."""

    name: str
    reason: str


@dataclass(frozen=True)
class SwitchPool:
    """Tell the broker: the pool is (in)active, takes a new policy, or new parameters for
    its workers to apply in place (None: unchanged)."""

    pool: str
    active: bool | None = None
    policy: str | None = None
    params: Mapping[str, Any] | None = None
    min_interval_s: float | None = None


@dataclass(frozen=True)
class LevelChanged:
    """The degradation ladder moved (or was forced): log it, tell the broker (and through
    its stats, every view and the modem's health record)."""

    level: str
    reason: str
    forced: bool = False


@dataclass(frozen=True)
class Reconfigure:
    """This worker's pool has new parameters: every later start uses them, and with
    `restart` the running process is stopped now and started again (outside its restart
    budget); without, it applies them in place (a SwitchPool with the params follows)."""

    name: str
    pool: str
    params: Mapping[str, Any]
    restart: bool = True


Action = Spawn | Kill | WorkerGone | GiveUp | Retry | Stop | AddWorker | Retire | SwitchPool \
    | Reconfigure | LevelChanged


class Refused(ValueError):
    """A control command that cannot apply now; the message says why and what would."""


@dataclass(frozen=True)
class Event:
    """One entry of the supervision timeline (give-ups, retries, capped restarts)."""

    t: float
    node: str
    kind: str  # "gave_up", "retry", "capped", "control", "level", "recycled"
    reason: str


# --- per-node state -------------------------------------------------------------------------


@dataclass
class NodeState:
    """What the supervisor knows about one node."""

    plan: NodePlan
    state: Lifecycle = Lifecycle.UNCONFIGURED
    reason: str = ""
    pid: int | None = None
    running: bool = False  # a process was spawned and has not been seen to exit
    started: float = 0.0
    last_beat: float = 0.0
    restarts: deque[float] = field(default_factory=deque)  # restart times inside the window
    restart_total: int = 0
    restart_at: float | None = None
    retry_at: float | None = None  # given up: retried then
    gave_up: int = 0
    retried: int = 0
    finished: bool = False  # ended on purpose (a finite source exhausted)
    retired: bool = False  # its pool shrank: stopped on purpose, never restarted
    reconfiguring: bool = False  # restarted on purpose with new parameters
    recycled: int = 0  # replaced on purpose (max_rss_mb, max_jobs), outside the budget

    @property
    def pool(self) -> str:
        return self.plan.pool

    @property
    def name(self) -> str:
        return self.plan.name

    def limit(self) -> float:
        """Silence allowed now: start-up time while configuring, else the liveness limit."""
        return self.plan.startup_s if self.state == Lifecycle.UNCONFIGURED else \
            self.plan.liveness_s


@dataclass
class PoolState:
    """A pool as runtime control sees it: lifecycle, size, policy, parameters."""

    name: str
    count: int
    policy: str
    params: dict[str, Any]
    liveness_s: float
    state: Lifecycle = Lifecycle.ACTIVE
    changes: int = 0
    off_by: str = ""  # who deactivated it: "operator" or "ladder" ("" while active)
    min_interval_s: float = 0.0  # the ladder's, at its current level


def worker_name(pool: str, index: int) -> str:
    """A worker node's name (its index within the pool)."""
    return f"worker:{pool}:{index}"


class SupervisorState:
    """Lifecycle, liveness and restart decisions for every node of one pipeline."""

    def __init__(self, plans: Iterable[NodePlan], budget: Budget) -> None:
        self.nodes = {p.name: NodeState(p) for p in plans}
        self.budget = budget
        self.timeline: deque[Event] = deque(maxlen=MAX_TIMELINE)
        self._counts = {"gave_up": 0, "retry": 0, "capped": 0, "control": 0, "level": 0,
                        "recycled": 0}
        self.stopping = False
        self.pools: dict[str, PoolState] = {}
        self.ladder: Ladder | None = None  # set by the shell when the ladder is enabled
        # Workers recycled per pool, by why (rss, jobs).
        self.recycled: dict[str, dict[str, int]] = {}

    def add(self, plan: NodePlan) -> None:
        """One more node to supervise (not spawned yet)."""
        self.nodes[plan.name] = NodeState(plan)

    def node(self, name: str) -> NodeState:
        return self.nodes[name]

    # --- events -----------------------------------------------------------------------

    def spawned(self, name: str, pid: int, now: float) -> None:
        """The shell started the node's process."""
        n = self.nodes[name]
        n.pid, n.running, n.started, n.last_beat = pid, True, now, now
        n.state, n.reason, n.restart_at = Lifecycle.UNCONFIGURED, "", None

    def heartbeat(self, name: str, pid: int, state: str, reason: str, now: float) -> bool:
        """A node reports its state; False when it is no current node process (ignored)."""
        n = self.nodes.get(name)
        life = Lifecycle.parse(state)
        if n is None or life is None or not n.running or n.pid != pid:
            return False
        n.last_beat, n.state, n.reason = now, life, reason
        return True

    def exited(self, name: str, code: int | None, now: float) -> list[Action]:
        """The node's process ended with `code`: finished, restarted, or given up."""
        n = self.nodes[name]
        if not n.running:
            return []
        n.running = False
        if code == 0 and n.plan.role == "capture" and n.state == Lifecycle.FINALIZED:
            n.finished = True
            return []
        if self.stopping:
            return []
        actions: list[Action] = []
        why = RECYCLE_EXITS.get(code, "") if code is not None else ""
        if n.plan.role == "worker" and why and not n.retired:
            # Planned: replaced at once, no back-off, the restart budget untouched.
            n.recycled += 1
            per_pool = self.recycled.setdefault(n.pool, {})
            per_pool[why] = per_pool.get(why, 0) + 1
            n.state, n.reason, n.reconfiguring = Lifecycle.INACTIVE, f"recycled ({why})", False
            self._note(now, name, "recycled", f"recycled ({why}): exit status {code}")
            return [WorkerGone(name, f"recycled ({why})", recycled=why),
                    Spawn(name, n.restart_total, recycled=why)]
        if n.plan.role == "worker":
            actions.append(WorkerGone(name, f"process exited with status {code}"))
        if n.retired:
            n.finished, n.state, n.reason = True, Lifecycle.FINALIZED, "retired: pool shrank"
            return actions
        if n.reconfiguring:  # stopped on purpose: back at once, outside the budget
            n.reconfiguring = False
            n.state, n.reason = Lifecycle.INACTIVE, "restarting with new parameters"
            n.restart_total += 1
            return [*actions, Spawn(name, n.restart_total)]
        b = self.budget
        while n.restarts and now - n.restarts[0] > b.window_s:
            n.restarts.popleft()
        if len(n.restarts) >= b.max_restarts:
            spent = (f"{len(n.restarts)} restarts in {b.window_s:g} s "
                     f"(last exit status {code})")
            if not n.plan.essential:
                n.gave_up += 1
                n.retry_at = now + b.cooldown_s
                n.state = Lifecycle.FINALIZED
                n.reason = f"gave up after {spent}; retry in {b.cooldown_s:g} s"
                self._note(now, name, "gave_up", n.reason)
                actions.append(GiveUp(name, n.reason, n.retry_at))
                return actions
            # Essential: never abandoned, restarted at the capped back-off instead.
            delay = b.backoff_max_s
            self._note(now, name, "capped", f"{spent}; essential, restart in {delay:g} s")
            n.restarts.popleft()
        else:
            delay = min(b.backoff_s * 2 ** len(n.restarts), b.backoff_max_s)
        n.restarts.append(now)
        n.restart_total += 1
        n.state, n.reason = Lifecycle.INACTIVE, f"exited with status {code}; " \
            f"restart in {delay:.1f} s"
        n.restart_at = now + delay
        return actions

    def finish(self, name: str) -> None:
        """The node's process ended on purpose (a tiny finite source, done during start-up)."""
        n = self.nodes[name]
        n.running, n.finished = False, True

    def tick(self, now: float) -> list[Action]:
        """Time passes: silent nodes are killed, due restarts and retries spawned."""
        actions: list[Action] = []
        if self.stopping:
            return actions
        for n in self.nodes.values():
            if n.finished:
                continue
            if n.running:
                silent = now - n.last_beat
                if silent > n.limit():
                    what = "not configured" if n.state == Lifecycle.UNCONFIGURED else "silent"
                    actions.append(Kill(n.name, f"{what} for {silent:.1f} s"))
                    n.last_beat = now  # one kill per limit: the exit follows
                continue
            if n.retry_at is not None and now >= n.retry_at:
                n.retry_at = None
                n.retried += 1
                n.restarts.clear()
                n.restart_total += 1
                reason = f"retrying after a cool-down of {self.budget.cooldown_s:g} s " \
                    f"(give-up {n.gave_up})"
                self._note(now, n.name, "retry", reason)
                actions += [Retry(n.name, reason), Spawn(n.name, n.restart_total)]
            elif n.restart_at is not None and now >= n.restart_at:
                n.restart_at = None
                actions.append(Spawn(n.name, n.restart_total))
        return actions

    def stop(self, reason: str) -> list[Action]:
        """A stop command (control socket, signal, duration, drained source)."""
        if self.stopping:
            return []
        self.stopping = True
        return [Stop(reason)]

    # --- runtime control ----------------------------------------------------------------

    def add_pool(self, name: str, count: int, policy: str, params: Mapping[str, Any],
                 liveness_s: float) -> None:
        """A pool started at boot (its workers are added as nodes by the caller)."""
        self.pools[name] = PoolState(name, count, policy, dict(params), liveness_s)

    def _pool(self, name: str) -> PoolState:
        p = self.pools.get(name)
        if p is None:
            started = ", ".join(sorted(self.pools)) or "none"
            raise Refused(f"no pool {name!r} in this run (pools started: {started}); "
                          "a pool with count 0 at start has no broker queue: start it "
                          "with a count of at least 1")
        if self.stopping:
            raise Refused(f"pool {name!r}: the pipeline is stopping; no changes now")
        return p

    def _control(self, now: float, pool: PoolState, what: str) -> None:
        pool.changes += 1
        self._note(now, f"pool:{pool.name}", "control", what)

    def set_count(self, name: str, count: int, now: float) -> list[Action]:
        """Grow or shrink a pool to `count` workers (the highest indices go first)."""
        p = self._pool(name)
        if not 1 <= count <= MAX_POOL_COUNT:
            raise Refused(f"pool {name!r}: count must be 1..{MAX_POOL_COUNT}, got {count}; "
                          "to stop its work without losing the pool, use --deactivate")
        if count == p.count:
            raise Refused(f"pool {name!r} already has {count} workers")
        actions: list[Action] = []
        for i in range(p.count, count):
            wname = worker_name(name, i)
            n = self.nodes.get(wname)
            if n is not None and n.running:  # still stopping from an earlier shrink
                raise Refused(f"pool {name!r}: {wname} is still stopping; try again in a "
                              "few seconds")
            self.nodes[wname] = NodeState(NodePlan(wname, "worker", p.liveness_s,
                                                   pool=name))
            actions += [AddWorker(wname, name, i), Spawn(wname, 0)]
        for i in range(count, p.count):
            wname = worker_name(name, i)
            n = self.nodes[wname]
            n.retired, n.restart_at, n.retry_at = True, None, None
            if n.running:
                actions.append(Retire(wname, f"pool {name} shrank to {count}"))
            else:
                n.finished, n.state = True, Lifecycle.FINALIZED
        self._control(now, p, f"count {p.count} -> {count}")
        p.count = count
        return actions

    def set_active(self, name: str, active: bool, now: float) -> list[Action]:
        """activate/deactivate, as a ROS 2 lifecycle node moves between active and inactive:
        an inactive pool's workers keep their models loaded and get no pairs."""
        p = self._pool(name)
        want = Lifecycle.ACTIVE if active else Lifecycle.INACTIVE
        if not active and p.state == Lifecycle.INACTIVE and p.off_by == "ladder":
            # Off already: the operator takes it over, so no level change turns it back on.
            self._control(now, p, "deactivated (held by the operator; the ladder had "
                                  "switched it off)")
            p.off_by = "operator"
            return []
        if p.state == want:
            verb = "activate" if active else "deactivate"
            raise Refused(f"pool {name!r} is {p.state}: {verb} is a transition from "
                          f"{'inactive' if active else 'active'} (ROS 2 lifecycle); "
                          "nothing to do")
        self._control(now, p, f"{'activated' if active else 'deactivated'} "
                              f"(was {p.state})")
        p.state = want
        p.off_by = "" if active else "operator"
        return [SwitchPool(name, active=active)]

    def set_policy(self, name: str, policy: str, now: float) -> list[Action]:
        """A new queueing policy for the pool's pending pairs (the broker applies it)."""
        p = self._pool(name)
        try:
            parse_policy(policy)
        except ValueError as exc:
            raise Refused(f"pool {name!r}: {exc}") from None
        if policy == p.policy:
            raise Refused(f"pool {name!r} already has policy {policy!r}")
        self._control(now, p, f"policy {p.policy} -> {policy}")
        p.policy = policy
        return [SwitchPool(name, policy=policy)]

    def set_param(self, name: str, key: str, value: Any, now: float,
                  in_place: bool = False) -> list[Action]:
        """One plugin parameter changed. A plugin that can be configured again
        (`in_place`) gets the pool's new parameters between pairs; otherwise every worker
        of the pool restarts with them."""
        p = self._pool(name)
        if key in p.params and p.params[key] == value:
            raise Refused(f"pool {name!r}: {key} is already {value!r}")
        before = p.params.get(key, "(default)")
        p.params[key] = value
        how = "reconfigured in place" if in_place else "restarting workers"
        self._control(now, p, f"param {key}: {before!r} -> {value!r}; {how}")
        actions: list[Action] = []
        for i in range(p.count):
            n = self.nodes[worker_name(name, i)]
            actions.append(Reconfigure(n.name, name, dict(p.params), restart=not in_place))
            if n.running and not in_place:
                n.reconfiguring = True
        if in_place:
            actions.append(SwitchPool(name, params=dict(p.params)))
        return actions

    def pool_view(self) -> dict[str, dict[str, Any]]:
        """Every pool's control state, for status and the ledger."""
        return {p.name: {"state": str(p.state), "count": p.count, "policy": p.policy,
                         "params": dict(p.params), "changes": p.changes, "off_by": p.off_by,
                         "min_interval_s": p.min_interval_s}
                for p in self.pools.values()}

    # --- degradation ladder ---------------------------------------------------------------

    def degrade(self, readings: Readings, now: float) -> list[Action]:
        """A snapshot of the sensors: the ladder may step one level (see trapflow.ladder)."""
        if self.ladder is None or self.stopping:
            return []
        step = self.ladder.update(readings, now)
        return self._level(now) if step.changed else []

    def force_level(self, level: str, now: float) -> list[Action]:
        """The operator's `trapflow level NAME|auto`; Refused for an unknown level."""
        if self.ladder is None:
            raise Refused("no degradation ladder in this run: it is off in the config "
                          "(ladder.enabled: false)")
        if self.stopping:
            raise Refused("the pipeline is stopping; no changes now")
        try:
            step = self.ladder.force(level, now)
        except ValueError as exc:
            raise Refused(str(exc)) from None
        if step.changed:
            return self._level(now, forced=True)
        self._note(now, "ladder", "level", f"{self.ladder.level}: {self.ladder.reason}")
        return []

    def _level(self, now: float, forced: bool = False) -> list[Action]:
        """Pools to the ladder's new level (the operator's rule in the module docstring)."""
        assert self.ladder is not None
        plan = self.ladder.plan()
        actions: list[Action] = []
        for p in self.pools.values():
            want = plan.get(p.name, PoolLevel())
            active: bool | None = None
            if not want.active and p.state == Lifecycle.ACTIVE:
                p.state, p.off_by, active = Lifecycle.INACTIVE, "ladder", False
            elif want.active and p.state == Lifecycle.INACTIVE and p.off_by == "ladder":
                p.state, p.off_by, active = Lifecycle.ACTIVE, "", True
            interval = None
            if want.min_interval_s != p.min_interval_s:
                p.min_interval_s = interval = want.min_interval_s
            if active is not None or interval is not None:
                actions.append(SwitchPool(p.name, active=active, min_interval_s=interval))
        self._note(now, "ladder", "level", self.ladder.reason)
        return [*actions, LevelChanged(self.ladder.level, self.ladder.reason, forced)]

    def ladder_view(self) -> dict[str, Any] | None:
        """The ladder's level, why, whether forced and its changes, for status and the
        ledger (None: no ladder)."""
        if self.ladder is None:
            return None
        lad = self.ladder
        return {"level": lad.level, "index": lad.index, "levels": list(lad.names),
                "reason": lad.reason, "forced": lad.forced, "changes": lad.changes}

    # --- start-up -------------------------------------------------------------------------

    def start_problem(self, names: Iterable[str], now: float) -> str | None:
        """Why start-up of these (spawned) nodes failed, or None while it may still succeed:
        a node that reports it cannot start, or one not active by its start-up deadline."""
        for name in names:
            n = self.nodes[name]
            if n.state == Lifecycle.INACTIVE and n.reason:
                return f"{name} cannot start: {n.reason}"
        slow = [name for name in names if self.nodes[name].state == Lifecycle.UNCONFIGURED
                and now - self.nodes[name].started > self.nodes[name].plan.startup_s]
        if slow:
            return f"nodes not active after {STARTUP_TIMEOUT_S:g} s: {slow}"
        return None

    def started(self, names: Iterable[str]) -> bool:
        """Every one of these nodes is active (or, a finite source, already done)."""
        return all(self.nodes[n].state in (Lifecycle.ACTIVE, Lifecycle.FINALIZED)
                   or self.nodes[n].finished for n in names)

    # --- read-outs --------------------------------------------------------------------------

    def _note(self, now: float, name: str, kind: str, reason: str) -> None:
        self.timeline.append(Event(now, name, kind, reason))
        self._counts[kind] += 1

    def counts(self) -> dict[str, int]:
        """Give-ups, retries, capped restarts, control changes and recycles over the run
        (the timeline keeps the last)."""
        return dict(self._counts)


@dataclass
class DurationClock:
    """When `--duration` ends a run: that long after the first pair capture sent (boot and
    model loading are not counted), or, when no pair comes at all, that long after capture
    became active (a source that never delivers still ends)."""

    duration: float | None
    active_at: float  # capture active (monotonic seconds)
    end: float | None = None

    def due(self, now: float, produced: int) -> bool:
        """Whether the run should stop now, given the pairs capture has sent so far."""
        if self.duration is None:
            return False
        if self.end is None:
            if produced > 0:
                self.end = now + self.duration
            elif now >= self.active_at + self.duration:
                self.end = now
        return self.end is not None and now >= self.end
