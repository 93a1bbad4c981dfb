"""The supervisor cores' vocabulary: restart budgets, node plans
and per-node state, the actions the cores return and the refusal they raise. No logic
beyond reading them; the decisions are trapflow.supervisor.state's and
trapflow.supervisor.pool_control's.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from trapflow.runtime.lifecycle import Lifecycle

# Roles the pipeline cannot do without: never given up while the supervisor lives.
ESSENTIAL_ROLES = frozenset({"broker", "capture", "normalizer"})
# How long every node has to report its first state before start-up is declared failed.
STARTUP_TIMEOUT_S = 60.0
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


# What the node core (supervisor.state) decides: restarts, kills, give-ups, the stop.
NodeAction = Spawn | Kill | WorkerGone | GiveUp | Retry | Stop
# What pool control and the ladder (supervisor.pool_control) decide.
PoolAction = AddWorker | Spawn | Retire | SwitchPool | Reconfigure | LevelChanged
# Everything the shell applies (Supervisor._act dispatches over every member).
Action = NodeAction | PoolAction


class Refused(ValueError):
    """A control command that cannot apply now; the message says why and what would."""


@dataclass(frozen=True)
class Event:
    """One entry of the supervision timeline (give-ups, retries, capped restarts)."""

    t: float
    node: str
    kind: str  # "gave_up", "retry", "capped", "control", "level", "recycled", "clock_step"
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
