"""Runtime pool control and the degradation ladder, decided purely: the part of the
supervisor core that owns the pools. No processes, sockets or clocks: callers pass `now`.

Runtime control (`trapflow pool`, `trapflow param`) is decided here: per pool its
lifecycle (active/inactive, moved as a ROS 2 lifecycle node moves: deactivate only from
active, activate only from inactive), its worker count, policy and parameters. A command
that cannot apply raises Refused (with what was expected and the fix); one that applies
returns actions (add or retire workers, tell the broker, restart the pool's workers with
new parameters) and one "control" entry in the timeline.

The degradation ladder (trapflow.supervisor.ladder) is applied here: a level change deactivates the
pools the new level switches off, activates again those the ladder itself had switched off,
sets each pool's minimum interval between pairs, and leaves one "level" entry. The rule
with the operator: the ladder never activates a pool the operator deactivated (it stays
inactive whatever the level until the operator activates it; deactivating a pool the ladder
has off takes it over); a pool the operator activates while the ladder has it off runs
until the next level change.

PoolControl is held by trapflow.supervisor.state.SupervisorState, which owns the nodes, the
timeline and whether the pipeline is stopping: it hands this part the node table, its
timeline note and a question for `stopping` at construction.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from trapflow.config.ladder import PoolLevel
from trapflow.config.schema import parse_policy
from trapflow.runtime.lifecycle import Lifecycle
from trapflow.supervisor.actions import (
    STARTUP_TIMEOUT_S,
    AddWorker,
    LevelChanged,
    NodePlan,
    NodeState,
    PoolAction,
    Reconfigure,
    Refused,
    Retire,
    Spawn,
    SwitchPool,
)
from trapflow.supervisor.ladder import Ladder, Readings

# Workers one pool may have (config's PoolConfig.count bound).
MAX_POOL_COUNT = 64


@dataclass
class PoolState:
    """A pool as runtime control sees it: lifecycle, size, policy, parameters."""

    name: str
    count: int
    policy: str
    params: dict[str, Any]
    liveness_s: float
    startup_s: float = STARTUP_TIMEOUT_S
    state: Lifecycle = Lifecycle.ACTIVE
    changes: int = 0
    off_by: str = ""  # who deactivated it: "operator" or "ladder" ("" while active)
    min_interval_s: float = 0.0  # the ladder's, at its current level


def worker_name(pool: str, index: int) -> str:
    """A worker node's name (its index within the pool)."""
    return f"worker:{pool}:{index}"


# A timeline entry: (now, node, kind, reason).
Note = Callable[[float, str, str, str], None]


class PoolControl:
    """Runtime control of the pools (`trapflow pool`, `trapflow param`) and the ladder's
    levels; the nodes, the timeline and `stopping` are the supervisor core's, lent here."""

    def __init__(self, nodes: dict[str, NodeState], note: Note, stopping: Callable[[], bool],
                 ladder: Ladder | None = None) -> None:
        self.nodes = nodes  # the core's node table: workers added and retired here
        self._note = note
        self._stopping = stopping
        self.by_name: dict[str, PoolState] = {}
        self.ladder = ladder  # None: the ladder is off in the config

    @property
    def stopping(self) -> bool:
        return self._stopping()

    # --- runtime control ----------------------------------------------------------------

    def add_pool(self, name: str, count: int, policy: str, params: Mapping[str, Any],
                 liveness_s: float, startup_s: float = STARTUP_TIMEOUT_S) -> None:
        """A pool started at boot (its workers are added as nodes by the caller)."""
        self.by_name[name] = PoolState(name, count, policy, dict(params), liveness_s,
                                       startup_s)

    def _pool(self, name: str) -> PoolState:
        p = self.by_name.get(name)
        if p is None:
            started = ", ".join(sorted(self.by_name)) or "none"
            raise Refused(f"no pool {name!r} in this run (pools started: {started}); "
                          "a pool with count 0 at start has no broker queue: start it "
                          "with a count of at least 1")
        if self.stopping:
            raise Refused(f"pool {name!r}: the pipeline is stopping; no changes now")
        return p

    def _control(self, now: float, pool: PoolState, what: str) -> None:
        pool.changes += 1
        self._note(now, f"pool:{pool.name}", "control", what)

    def set_count(self, name: str, count: int, now: float) -> list[PoolAction]:
        """Grow or shrink a pool to `count` workers (the highest indices go first)."""
        p = self._pool(name)
        if not 1 <= count <= MAX_POOL_COUNT:
            raise Refused(f"pool {name!r}: count must be 1..{MAX_POOL_COUNT}, got {count}; "
                          "to stop its work without losing the pool, use --deactivate")
        if count == p.count:
            raise Refused(f"pool {name!r} already has {count} workers")
        actions: list[PoolAction] = []
        for i in range(p.count, count):
            wname = worker_name(name, i)
            n = self.nodes.get(wname)
            if n is not None and n.running:  # still stopping from an earlier shrink
                raise Refused(f"pool {name!r}: {wname} is still stopping; try again in a "
                              "few seconds")
            self.nodes[wname] = NodeState(NodePlan(wname, "worker", p.liveness_s,
                                                   pool=name, startup_s=p.startup_s))
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

    def set_active(self, name: str, active: bool, now: float) -> list[PoolAction]:
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

    def set_policy(self, name: str, policy: str, now: float) -> list[PoolAction]:
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
                  in_place: bool = False) -> list[PoolAction]:
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
        actions: list[PoolAction] = []
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
                for p in self.by_name.values()}

    # --- degradation ladder ---------------------------------------------------------------

    def degrade(self, readings: Readings, now: float) -> list[PoolAction]:
        """A snapshot of the sensors: the ladder may step one level (see supervisor.ladder)."""
        if self.ladder is None or self.stopping:
            return []
        step = self.ladder.update(readings, now)
        return self._level(now) if step.changed else []

    def force_level(self, level: str, now: float) -> list[PoolAction]:
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

    def _level(self, now: float, forced: bool = False) -> list[PoolAction]:
        """Pools to the ladder's new level (the operator's rule in the module docstring)."""
        assert self.ladder is not None
        plan = self.ladder.plan()
        actions: list[PoolAction] = []
        for p in self.by_name.values():
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
