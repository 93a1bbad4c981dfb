"""The supervisor's decisions without processes: liveness, start-up, restart budget, back-off,
give-up and retry after a cool-down, essential nodes that are never abandoned."""

from __future__ import annotations

import pytest

from trapflow.runtime.lifecycle import EXIT_RECYCLED_JOBS, EXIT_RECYCLED_RSS, Lifecycle
from trapflow.supervisor.actions import (
    Budget,
    GiveUp,
    Kill,
    NodePlan,
    Retry,
    Spawn,
    Stop,
    WorkerGone,
)
from trapflow.supervisor.state import SupervisorState

BUDGET = Budget(max_restarts=2, window_s=60.0, backoff_s=0.5, backoff_max_s=4.0,
                cooldown_s=30.0)


def core(*plans: NodePlan, budget: Budget = BUDGET) -> SupervisorState:
    return SupervisorState(plans or (NodePlan("worker:vo:0", "worker", liveness_s=3.0),),
                           budget)


def up(s: SupervisorState, name: str, pid: int, now: float,
       state: str = Lifecycle.ACTIVE) -> None:
    s.spawned(name, pid, now)
    assert s.heartbeat(name, pid, state, "", now)


def kinds(actions: list[object]) -> list[str]:
    return [type(a).__name__ for a in actions]


def crash_until_spawn(s: SupervisorState, name: str, pid: int, now: float) -> float:
    """The node's process exits with 1 at `now`; tick until the core spawns it again."""
    s.exited(name, 1, now)
    t = now
    while not any(isinstance(a, Spawn) for a in s.tick(t)):
        t += 0.25
        assert t < now + 1000, "never respawned"
    up(s, name, pid, t)
    return t


# --- heartbeats ----------------------------------------------------------------------------


@pytest.mark.parametrize(("name", "pid", "state", "accepted"), [
    ("worker:vo:0", 10, "active", True),
    ("worker:vo:0", 11, "active", False),  # a dead predecessor's last heartbeat
    ("worker:vo:9", 10, "active", False),  # no such node
    ("worker:vo:0", 10, "dancing", False),  # no such state
    ("worker:vo:0", 10, "finalized", True),
])
def test_heartbeats_are_taken_only_from_the_current_process(
        name: str, pid: int, state: str, accepted: bool) -> None:
    s = core()
    s.spawned("worker:vo:0", 10, 0.0)
    assert s.heartbeat(name, pid, state, "why", 1.0) is accepted
    node = s.node("worker:vo:0")
    assert node.state == (Lifecycle(state) if accepted else Lifecycle.UNCONFIGURED)
    assert isinstance(node.state, Lifecycle)


# --- liveness ------------------------------------------------------------------------------


@pytest.mark.parametrize(("state", "silent_s", "killed"), [
    (Lifecycle.ACTIVE, 2.9, False),
    (Lifecycle.ACTIVE, 3.1, True),  # its pool's timeout_s, not a 60 s start-up allowance
    (Lifecycle.INACTIVE, 3.1, True),
    (Lifecycle.UNCONFIGURED, 30.0, False),  # still loading a model: start-up time
    (Lifecycle.UNCONFIGURED, 60.5, True),
])
def test_liveness_by_state(state: Lifecycle, silent_s: float, killed: bool) -> None:
    """Regression (issue 16, item 9): a worker that took work counts as active, so a hang on
    its first pair is killed after its limit, not after the 60 s start-up allowance."""
    s = core()
    up(s, "worker:vo:0", 10, 0.0, state)
    acts = s.tick(silent_s)
    assert kinds(acts) == (["Kill"] if killed else [])
    assert s.tick(silent_s + 0.1) == []  # one kill, then the exit is awaited


def test_a_beat_resets_the_silence() -> None:
    s = core()
    up(s, "worker:vo:0", 10, 0.0)
    s.heartbeat("worker:vo:0", 10, "active", "", 2.5)
    assert s.tick(5.0) == []
    assert isinstance(s.tick(5.6)[0], Kill)


# --- restarts, back-off, budget ----------------------------------------------------------


def test_a_crashed_worker_is_reported_gone_and_restarted_with_doubling_backoff() -> None:
    s = core(budget=Budget(max_restarts=5, window_s=60, backoff_s=0.5, backoff_max_s=1.5))
    up(s, "worker:vo:0", 10, 0.0)
    acts = s.exited("worker:vo:0", -9, 1.0)
    assert acts == [WorkerGone("worker:vo:0", "process exited with status -9")]
    delays = []
    t = 1.0
    for pid in range(11, 15):
        t0 = t
        t = crash_until_spawn(s, "worker:vo:0", pid, t)
        delays.append(t - t0)
    assert delays == [0.5, 1.0, 1.5, 1.5]  # 0.5 doubling, capped at backoff_max_s
    assert s.node("worker:vo:0").restart_total == 4


@pytest.mark.parametrize(("role", "gives_up"), [
    ("worker", True), ("events", True), ("modem", True),
    ("broker", False), ("capture", False), ("normalizer", False),
])
def test_budget_spent_gives_up_only_ordinary_nodes(role: str, gives_up: bool) -> None:
    """Regression (issue 16, item 3): the broker's give-up ended the run; essential nodes
    now keep restarting at the capped back-off, and nothing asks the pipeline to stop."""
    name = role if role != "worker" else "worker:vo:0"
    s = core(NodePlan(name, role, liveness_s=5.0))
    up(s, name, 1, 0.0)
    t = crash_until_spawn(s, name, 2, 1.0)
    t = crash_until_spawn(s, name, 3, t + 1)
    acts = s.exited(name, 1, t + 1)  # the third exit inside the window: budget spent
    node = s.node(name)
    assert not any(isinstance(a, Stop) for a in acts)
    if gives_up:
        assert kinds(acts)[-1] == "GiveUp"
        assert node.state == Lifecycle.FINALIZED
        assert node.reason.startswith("gave up after 2 restarts in 60 s (last exit status 1)")
        assert s.tick(t + 20) == []  # cooling down
        assert s.counts() == {"gave_up": 1, "retry": 0, "capped": 0, "control": 0, "level": 0,
                                "recycled": 0}
    else:
        assert node.restart_at == t + 1 + BUDGET.backoff_max_s  # capped back-off
        assert node.state == Lifecycle.INACTIVE
        assert s.counts() == {"gave_up": 0, "retry": 0, "capped": 1, "control": 0, "level": 0,
                                "recycled": 0}
        # ...and it never stops trying: ten more crashes, ten more spawns.
        t += 1
        for pid in range(4, 14):
            t = crash_until_spawn(s, name, pid, t) + 0.1
        assert s.counts()["gave_up"] == 0


def test_a_given_up_node_is_retried_after_the_cooldown_with_a_fresh_budget() -> None:
    """Regression (issue 16, item 3): give-ups were permanent (vo produced nothing for the
    last 96 s of a kill storm)."""
    s = core()
    up(s, "worker:vo:0", 1, 0.0)
    t = crash_until_spawn(s, "worker:vo:0", 2, 1.0)
    t = crash_until_spawn(s, "worker:vo:0", 3, t + 1)
    acts = s.exited("worker:vo:0", 1, t + 1)
    give = next(a for a in acts if isinstance(a, GiveUp))
    assert give.retry_at == t + 1 + BUDGET.cooldown_s
    assert s.tick(give.retry_at - 0.1) == []
    acts = s.tick(give.retry_at)
    assert kinds(acts) == ["Retry", "Spawn"]
    assert isinstance(acts[0], Retry) and "cool-down of 30 s" in acts[0].reason
    up(s, "worker:vo:0", 4, give.retry_at)
    # A fresh budget: the next crash restarts it after the first back-off step.
    s.exited("worker:vo:0", 1, give.retry_at + 1)
    assert s.node("worker:vo:0").restart_at == give.retry_at + 1 + BUDGET.backoff_s
    assert [e.kind for e in s.timeline] == ["gave_up", "retry"]
    assert s.node("worker:vo:0").gave_up == 1 and s.node("worker:vo:0").retried == 1


def test_restarts_outside_the_window_do_not_count() -> None:
    s = core(budget=Budget(max_restarts=1, window_s=10.0, backoff_s=0.0, cooldown_s=30))
    up(s, "worker:vo:0", 1, 0.0)
    t = crash_until_spawn(s, "worker:vo:0", 2, 1.0)
    acts = s.exited("worker:vo:0", 1, t + 11)  # the first restart left the window
    assert "GiveUp" not in kinds(acts)


# --- finishing, stopping, start-up ---------------------------------------------------------


@pytest.mark.parametrize(("state", "code", "finished"), [
    (Lifecycle.FINALIZED, 0, True),  # a finite source exhausted
    (Lifecycle.ACTIVE, 0, False),  # an unexpected exit: restarted
    (Lifecycle.FINALIZED, 1, False),
])
def test_capture_that_ends_on_purpose_is_not_restarted(state: Lifecycle, code: int,
                                                       finished: bool) -> None:
    s = core(NodePlan("capture", "capture", liveness_s=5.0))
    up(s, "capture", 1, 0.0, state)
    s.exited("capture", code, 1.0)
    assert s.node("capture").finished is finished
    assert (s.node("capture").restart_at is None) is finished
    assert s.tick(100.0) == ([] if finished else [Spawn("capture", 1)])


def test_nothing_restarts_once_stopping() -> None:
    s = core()
    up(s, "worker:vo:0", 1, 0.0)
    assert s.stop("signal") == [Stop("signal")]
    assert s.stop("again") == []
    assert s.exited("worker:vo:0", -15, 1.0) == []
    assert s.tick(100.0) == []


SLOW = "(a slow board or emulation: raise supervisor.startup_timeout_s)"


@pytest.mark.parametrize(("state", "reason", "at", "startup_s", "problem"), [
    (Lifecycle.ACTIVE, "", 1.0, 60.0, None),
    (Lifecycle.UNCONFIGURED, "", 59.0, 60.0, None),
    (Lifecycle.UNCONFIGURED, "", 61.0, 60.0,
     f"nodes not active after 60 s: ['worker:vo:0'] {SLOW}"),
    # supervisor.startup_timeout_s raised (issue 27: emulated arm64 starts in minutes)
    (Lifecycle.UNCONFIGURED, "", 61.0, 600.0, None),
    (Lifecycle.UNCONFIGURED, "", 601.0, 600.0,
     f"nodes not active after 600 s: ['worker:vo:0'] {SLOW}"),
    (Lifecycle.INACTIVE, "cannot start algorithm: no model", 1.0, 60.0,
     "worker:vo:0 cannot start: cannot start algorithm: no model"),
])
def test_start_up_deadline_and_reasons(state: Lifecycle, reason: str, at: float,
                                       startup_s: float, problem: str | None) -> None:
    s = core(NodePlan("worker:vo:0", "worker", liveness_s=3.0, startup_s=startup_s))
    s.spawned("worker:vo:0", 1, 0.0)
    s.heartbeat("worker:vo:0", 1, state, reason, 0.5)
    assert s.start_problem(["worker:vo:0"], at) == problem
    assert s.started(["worker:vo:0"]) is (state == Lifecycle.ACTIVE)


@pytest.mark.parametrize(("timeout_s", "heartbeat_s", "limit"), [
    (3.0, 1.0, 3.0),  # the pool's timeout_s, not supervisor.liveness_s (5 s)
    (10.0, 1.0, 10.0),
    (0.5, 1.0, 2.0),  # never under two idle heartbeats: an idle worker is not hung
])
def test_a_workers_liveness_is_its_pools_timeout(timeout_s: float, heartbeat_s: float,
                                                 limit: float) -> None:
    """Regression (issue 16, item 9): a hung worker lived until supervisor.liveness_s."""
    from trapflow.supervisor.shell import worker_liveness

    assert worker_liveness(timeout_s, heartbeat_s) == limit


# --- recycling (issue 14 part 6) --------------------------------------------------------------


@pytest.mark.parametrize(("code", "why"), [(EXIT_RECYCLED_RSS, "rss"),
                                           (EXIT_RECYCLED_JOBS, "jobs")])
def test_a_recycled_worker_is_replaced_at_once_outside_the_budget(code: int, why: str) -> None:
    """Recycling is planned: no back-off, no restart counted, the budget untouched, even
    many times in a row; counted per pool and why, and in the timeline."""
    s = core(NodePlan("worker:mono:0", "worker", 3.0, pool="mono"))
    t = 0.0
    for i in range(BUDGET.max_restarts * 3):
        up(s, "worker:mono:0", 10 + i, t)
        acts = s.exited("worker:mono:0", code, t + 0.1)
        assert acts == [WorkerGone("worker:mono:0", f"recycled ({why})", recycled=why),
                        Spawn("worker:mono:0", 0, recycled=why)]
        t += 0.2
    n = s.node("worker:mono:0")
    assert (n.restart_total, len(n.restarts), n.gave_up, n.restart_at) == (0, 0, 0, None)
    assert n.recycled == BUDGET.max_restarts * 3
    assert s.recycled == {"mono": {why: BUDGET.max_restarts * 3}}
    assert s.counts()["recycled"] == BUDGET.max_restarts * 3
    assert [e.kind for e in s.timeline] == ["recycled"] * (BUDGET.max_restarts * 3)
    # A real crash afterwards still meets a whole budget.
    up(s, "worker:mono:0", 99, t)
    acts = s.exited("worker:mono:0", 1, t + 0.1)
    assert kinds(acts) == ["WorkerGone"] and n.restart_at == pytest.approx(t + 0.1 + 0.5)


@pytest.mark.parametrize(("role", "code", "retired", "stopping", "expect"), [
    ("capture", EXIT_RECYCLED_RSS, False, False, []),  # not a worker: an ordinary exit
    ("worker", EXIT_RECYCLED_JOBS, True, False, ["WorkerGone"]),  # its pool shrank meanwhile
    ("worker", EXIT_RECYCLED_RSS, False, True, []),  # the pipeline is stopping
    ("worker", 0, False, False, ["WorkerGone"]),  # status 0 is no recycle
])
def test_recycle_status_only_recycles_a_live_pools_worker(
        role: str, code: int, retired: bool, stopping: bool, expect: list[str]) -> None:
    name = "worker:mono:0" if role == "worker" else role
    s = core(NodePlan(name, role, 3.0, pool="mono" if role == "worker" else ""))
    up(s, name, 10, 0.0)
    s.node(name).retired = retired
    if stopping:
        s.stop("test")
    assert kinds(s.exited(name, code, 0.1)) == expect
    assert s.recycled == {}
