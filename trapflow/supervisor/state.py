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

Runtime pool control and the degradation ladder are decided by the PoolControl this core
holds (`pools`, trapflow.supervisor.pool_control), over the same nodes and timeline; the
actions are trapflow.supervisor.actions'.
"""

from __future__ import annotations

import signal
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

from trapflow.errors import NodeDiedError, StartupError
from trapflow.runtime.lifecycle import RECYCLE_EXITS, Lifecycle
from trapflow.supervisor.actions import (
    Budget,
    Event,
    GiveUp,
    Kill,
    NodeAction,
    NodePlan,
    NodeState,
    Retry,
    Spawn,
    Stop,
    WorkerGone,
)
from trapflow.supervisor.ladder import Ladder
from trapflow.supervisor.pool_control import PoolControl

# Timeline entries kept for status and the ledger (the oldest go first).
MAX_TIMELINE = 1000


class SupervisorState:
    """Lifecycle, liveness and restart decisions for every node of one pipeline; runtime
    control of its pools and the ladder in `pools`."""

    def __init__(self, plans: Iterable[NodePlan], budget: Budget,
                 ladder: Ladder | None = None) -> None:
        self.nodes = {p.name: NodeState(p) for p in plans}
        self.budget = budget
        self.timeline: deque[Event] = deque(maxlen=MAX_TIMELINE)
        self._counts = {"gave_up": 0, "retry": 0, "capped": 0, "control": 0, "level": 0,
                        "recycled": 0}
        self.clock_steps = 0  # wall-clock steps seen (trapflow.runtime.clock_step)
        self.stopping = False
        self.pools = PoolControl(self.nodes, self._note, lambda: self.stopping, ladder)
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

    def exited(self, name: str, code: int | None, now: float) -> list[NodeAction]:
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
        actions: list[NodeAction] = []
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

    def tick(self, now: float) -> list[NodeAction]:
        """Time passes: silent nodes are killed, due restarts and retries spawned."""
        actions: list[NodeAction] = []
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

    def stop(self, reason: str) -> list[NodeAction]:
        """A stop command (control socket, signal, duration, drained source)."""
        if self.stopping:
            return []
        self.stopping = True
        return [Stop(reason)]

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
            limit = max(self.nodes[name].plan.startup_s for name in slow)
            return (f"nodes not active after {limit:g} s: {slow} (a slow board or emulation: "
                    "raise supervisor.startup_timeout_s)")
        return None

    def started(self, names: Iterable[str]) -> bool:
        """Every one of these nodes is active (or, a finite source, already done)."""
        return all(self.nodes[n].state in (Lifecycle.ACTIVE, Lifecycle.FINALIZED)
                   or self.nodes[n].finished for n in names)

    # --- read-outs --------------------------------------------------------------------------

    def _note(self, now: float, name: str, kind: str, reason: str) -> None:
        self.timeline.append(Event(now, name, kind, reason))
        self._counts[kind] += 1

    def clock_stepped(self, now: float, step_s: float) -> None:
        """The wall clock stepped (trapflow.runtime.clock_step): into the timeline."""
        self.timeline.append(Event(now, "clock", "clock_step",
                                   f"the wall clock stepped by {step_s:+.1f} s"))
        self.clock_steps += 1

    def counts(self) -> dict[str, int]:
        """Give-ups, retries, capped restarts, control changes and recycles over the run
        (the timeline keeps the last)."""
        return dict(self._counts)


def died_at_start(name: str, exitcode: int | None, reason: str
                  ) -> StartupError | NodeDiedError:
    """The error that ends a start-up in which a node died. Killed by a signal, or gone
    without saying why: a runtime failure (exit 1; a worker killed while the pipeline
    started ended the run with 2, a usage error, issue 36 item 6). Gone saying why it
    cannot start (a plugin that cannot load, a port taken): a start-up error (2)."""
    if exitcode is not None and exitcode < 0:
        try:
            how = f"killed by {signal.Signals(-exitcode).name}"
        except ValueError:
            how = f"killed by signal {-exitcode}"
        return NodeDiedError(f"{name} died while the pipeline started: {how}")
    if reason:
        return StartupError(f"{name} cannot start: {reason}")
    return NodeDiedError(f"{name} died while the pipeline started: exited with status "
                         f"{exitcode}")


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
