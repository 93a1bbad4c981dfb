"""Runtime control decided without processes: pool lifecycle (ROS 2 transitions), count,
policy and parameters in the supervision core; the broker's per-pool active flag; the
control requests' decoding with bounds."""

from __future__ import annotations

from typing import Any

import msgspec
import pytest

from trapflow.broker.state import BrokerState, Dispatch, PoolSpec, Release
from trapflow.config.schema import parse_policy
from trapflow.errors import ProtocolError
from trapflow.runtime.lifecycle import Lifecycle
from trapflow.supervisor.actions import (
    AddWorker,
    Budget,
    NodePlan,
    Reconfigure,
    Refused,
    Retire,
    Spawn,
    SwitchPool,
    WorkerGone,
)
from trapflow.supervisor.pool_control import worker_name
from trapflow.supervisor.state import SupervisorState
from trapflow.wire import control_msgs, messages
from trapflow.wire.control_client import parse_assignment


def core(count: int = 2, params: dict[str, Any] | None = None) -> SupervisorState:
    s = SupervisorState((), Budget(max_restarts=2))
    s.pools.add_pool("mono", count, "latest", params or {"conf": 0.25}, liveness_s=5.0)
    for i in range(count):
        name = worker_name("mono", i)
        s.add(NodePlan(name, "worker", 5.0, pool="mono"))
        s.spawned(name, 100 + i, 0.0)
        assert s.heartbeat(name, 100 + i, "active", "", 0.0)
    return s


def kinds(actions: list[object]) -> list[str]:
    return [type(a).__name__ for a in actions]


# --- the core: lifecycle transitions --------------------------------------------------------


@pytest.mark.parametrize(("steps", "refused_at"), [
    ([False], None),  # active -> inactive
    ([False, True], None),  # and back
    ([True], 0),  # activate an active pool: no such transition
    ([False, False], 1),  # deactivate an inactive one
    ([False, True, True], 2),
])
def test_lifecycle_transitions(steps: list[bool], refused_at: int | None) -> None:
    s = core()
    for i, active in enumerate(steps):
        if i == refused_at:
            with pytest.raises(Refused, match="ROS 2 lifecycle"):
                s.pools.set_active("mono", active, float(i))
            return
        assert s.pools.set_active("mono", active, float(i)) == [SwitchPool("mono", active=active)]
        assert s.pools.by_name["mono"].state == (Lifecycle.ACTIVE if active else Lifecycle.INACTIVE)
    assert refused_at is None
    assert [e.kind for e in s.timeline] == ["control"] * len(steps)
    assert s.counts()["control"] == len(steps)


# --- the core: count ------------------------------------------------------------------------


@pytest.mark.parametrize(("count", "expected"), [
    (4, ["AddWorker", "Spawn", "AddWorker", "Spawn"]),
    (1, ["Retire"]),
    (3, ["AddWorker", "Spawn"]),
])
def test_count_grows_and_shrinks_from_the_top(count: int, expected: list[str]) -> None:
    s = core(count=2)
    acts = s.pools.set_count("mono", count, 1.0)
    assert kinds(acts) == expected
    if count > 2:
        assert acts[0] == AddWorker("worker:mono:2", "mono", 2)
        assert acts[1] == Spawn("worker:mono:2", 0)
        assert s.node("worker:mono:2").pool == "mono"
    else:
        assert acts == [Retire("worker:mono:1", "pool mono shrank to 1")]
    assert s.pools.pool_view()["mono"]["count"] == count
    assert s.timeline[-1].reason == f"count 2 -> {count}"


def test_a_retired_worker_is_not_restarted_and_can_come_back() -> None:
    s = core(count=2)
    s.pools.set_count("mono", 1, 1.0)
    acts = s.exited("worker:mono:1", 0, 2.0)
    assert kinds(acts) == ["WorkerGone"]  # the broker forgets it at once
    n = s.node("worker:mono:1")
    assert n.finished and n.state == Lifecycle.FINALIZED
    assert s.heartbeat("worker:mono:0", 100, "active", "", 99.0)  # the one left is alive
    assert s.tick(100.0) == []  # the retired one: never respawned, never killed for silence
    assert kinds(s.pools.set_count("mono", 2, 101.0)) == ["AddWorker", "Spawn"]
    assert not s.node("worker:mono:1").retired


def test_growing_onto_a_worker_still_stopping_is_refused() -> None:
    s = core(count=2)
    s.pools.set_count("mono", 1, 1.0)  # worker 1 told to stop, not yet exited
    with pytest.raises(Refused, match="still stopping"):
        s.pools.set_count("mono", 2, 1.5)


# --- the core: parameters and policy ---------------------------------------------------------


def test_param_restarts_each_worker_outside_the_budget() -> None:
    s = core(count=2)
    acts = s.pools.set_param("mono", "conf", 0.9, 1.0)
    assert acts == [Reconfigure(worker_name("mono", i), "mono", {"conf": 0.9}) for i in (0, 1)]
    assert s.timeline[-1].reason == "param conf: 0.25 -> 0.9; restarting workers"
    for _ in range(5):  # more than the budget's 2 restarts: none is counted against it
        out = s.exited("worker:mono:0", 0, 2.0)
        assert kinds(out) == ["WorkerGone", "Spawn"]
        s.spawned("worker:mono:0", 200, 2.0)
        s.node("worker:mono:0").reconfiguring = True
    assert s.node("worker:mono:0").gave_up == 0


def test_param_in_place_reaches_the_workers_through_the_broker_without_a_restart() -> None:
    s = core(count=2)
    acts = s.pools.set_param("mono", "conf", 0.9, 1.0, in_place=True)
    assert acts == [
        *(Reconfigure(worker_name("mono", i), "mono", {"conf": 0.9}, restart=False)
          for i in (0, 1)),
        SwitchPool("mono", params={"conf": 0.9}),
    ]
    assert not any(s.node(worker_name("mono", i)).reconfiguring for i in (0, 1))
    assert s.timeline[-1].reason == "param conf: 0.25 -> 0.9; reconfigured in place"
    # a worker that exits afterwards (its plugin refused the values) is an ordinary crash
    assert kinds(s.exited("worker:mono:0", 0, 2.0)) == ["WorkerGone"]


def test_an_unplanned_exit_after_a_param_change_is_a_crash_again() -> None:
    s = core(count=1)
    s.pools.set_param("mono", "conf", 0.9, 1.0)
    assert kinds(s.exited("worker:mono:0", 0, 2.0)) == ["WorkerGone", "Spawn"]
    s.spawned("worker:mono:0", 201, 2.0)
    assert kinds(s.exited("worker:mono:0", 1, 3.0)) == ["WorkerGone"]  # back-off, no Spawn
    assert s.node("worker:mono:0").restart_at is not None


@pytest.mark.parametrize(("call", "args", "match"), [
    ("set_count", ("vo", 2), "no pool 'vo'"),
    ("set_count", ("mono", 0), r"count must be 1\.\.64"),
    ("set_count", ("mono", 65), r"count must be 1\.\.64"),
    ("set_count", ("mono", 2), "already has 2 workers"),
    ("set_policy", ("mono", "sometimes"), "pool 'mono'"),
    ("set_policy", ("mono", "latest"), "already has policy"),
    ("set_param", ("mono", "conf", 0.25), "already 0.25"),
    ("set_active", ("tags", False), "no pool 'tags'"),
])
def test_refused_commands_change_nothing(call: str, args: tuple[Any, ...], match: str) -> None:
    s = core(count=2)
    before = s.pools.pool_view()
    with pytest.raises(Refused, match=match):
        getattr(s.pools, call)(*args, 1.0)
    assert s.pools.pool_view() == before and not s.timeline


def test_nothing_changes_while_stopping() -> None:
    s = core()
    s.stop("test")
    with pytest.raises(Refused, match="stopping"):
        s.pools.set_active("mono", False, 1.0)


def test_policy_goes_to_the_broker() -> None:
    s = core()
    assert s.pools.set_policy("mono", "fifo:4", 1.0) == [SwitchPool("mono", policy="fifo:4")]
    assert s.pools.pool_view()["mono"]["policy"] == "fifo:4"


# --- the broker: a deactivated pool counts what it would have queued -------------------------


def broker(policy: str = "fifo:8") -> BrokerState:
    return BrokerState({"mono": PoolSpec(parse_policy(policy), 10.0),
                        "vo": PoolSpec(parse_policy("fifo:8"), 10.0)})


def test_inactive_pool_counts_pairs_as_inactive_and_releases_them() -> None:
    b = broker()
    b.pair_arrived(0, 0.0)
    b.pair_arrived(1, 0.0)  # both pending in both pools (no workers)
    acts = b.set_active("mono", False, 1.0)
    assert acts == []  # vo still holds 0 and 1
    assert b.pool_stats()["mono"].inactive == 2 and b.pool_stats()["mono"].pending == 0
    b.pair_arrived(2, 2.0)
    st = b.pool_stats()["mono"]
    assert (st.received, st.inactive, st.dropped, st.active) == (3, 3, 0, False)
    assert b.held() == 3  # vo's
    assert b.pool_stats()["vo"].pending == 3


def test_an_inactive_only_pipeline_releases_every_pair() -> None:
    b = BrokerState({"mono": PoolSpec(parse_policy("latest"), 10.0)})
    b.set_active("mono", False, 0.0)
    assert b.pair_arrived(7, 1.0) == [Release(7)]
    assert b.drained()


def test_in_flight_pairs_finish_after_deactivation_and_work_resumes_on_activation() -> None:
    b = broker()
    assert b.worker_ready(b"w", "mono", 1, 0.0) == []
    assert b.pair_arrived(0, 0.0)[0] == Dispatch(b"w", "mono", 0, 0)
    b.set_active("mono", False, 0.5)
    b.job_done(b"w", "mono", 0, True, 1.0)
    assert b.pool_stats()["mono"].processed == 1
    b.pair_arrived(1, 1.5)
    b.set_active("mono", True, 2.0)
    acts = b.pair_arrived(2, 2.5)
    assert Dispatch(b"w", "mono", 2, 1) in acts
    st = b.pool_stats()["mono"]
    assert (st.processed, st.inactive, st.active) == (1, 1, True)


def test_a_new_policy_requeues_pending_and_counts_its_drops() -> None:
    b = broker("fifo:8")
    for seq in range(5):
        b.pair_arrived(seq, 0.0)
    b.set_policy("mono", "latest", 1.0)
    st = b.pool_stats()["mono"]
    assert (st.pending, st.dropped) == (1, 4)


@pytest.mark.parametrize(("call", "args"), [
    ("set_active", ("tags", False)),
    ("set_policy", ("tags", "latest")),
    ("set_policy", ("mono", "sometimes")),
])
def test_broker_refuses_unknown_pools_and_bad_policies(call: str, args: tuple[Any, ...]
                                                       ) -> None:
    b = broker()
    with pytest.raises(ValueError):
        getattr(b, call)(*args, 0.0)


# --- the wire: requests decoded with bounds --------------------------------------------------


def raw(obj: dict[str, Any]) -> bytes:
    return msgspec.msgpack.encode(obj)


@pytest.mark.parametrize(("data", "match"), [
    (raw({"type": "pool", "pool": "mono"}), "exactly one of count, policy, active"),
    (raw({"type": "pool", "pool": "mono", "count": 2, "active": False}), "exactly one"),
    (raw({"type": "pool", "pool": "mono", "count": 0}), ">= 1"),
    (raw({"type": "pool", "pool": "mono", "count": 65}), "<= 64"),
    (raw({"type": "pool", "pool": "", "count": 1}), "length >= 1"),
    (raw({"type": "pool", "pool": "x" * 65, "count": 1}), "length <= 64"),
    (raw({"type": "pool", "pool": "mo no", "count": 1}), "matching regex"),
    (raw({"type": "param", "pool": "mono", "key": "conf", "value": [1, 2]}), "Expected"),
    (raw({"type": "param", "pool": "mono", "key": "conf", "value": "x" * 300}), "length"),
    (raw({"type": "param", "pool": "mono", "key": "a\nb", "value": 1}), "matching regex"),
    (raw({"type": "reboot"}), "Invalid value 'reboot'"),
    (b"\x00" * 5000, "at most"),
])
def test_control_requests_are_decoded_with_bounds(data: bytes, match: str) -> None:
    with pytest.raises(ProtocolError, match=match):
        control_msgs.decode_control(data)


@pytest.mark.parametrize("req", [
    control_msgs.PoolRequest(pool="mono", count=3),
    control_msgs.PoolRequest(pool="mono", active=False),
    control_msgs.PoolRequest(pool="stereo", policy="fifo:4"),
    control_msgs.ParamRequest(pool="mono", key="conf_threshold", value=0.5),
    control_msgs.ParamRequest(pool="mono", key="labels", value="crab"),
    control_msgs.ParamRequest(pool="mono", key="debug", value=True),
])
def test_control_requests_round_trip(req: messages.Msg) -> None:
    assert control_msgs.decode_control(messages.encode(req)) == req


@pytest.mark.parametrize("msg", [
    messages.PoolSwitch(pool="mono", active=False),
    messages.PoolSwitch(pool="mono", policy="fifo:2"),
    messages.PoolSwitch(pool="mono", params={"confidence": 0.5, "input_size": [320, 320]}),
])
def test_a_pool_switch_is_a_worker_socket_message(msg: messages.PoolSwitch) -> None:
    assert messages.decode_worker_msg(messages.encode(msg)) == msg


@pytest.mark.parametrize(("data", "match"), [
    (raw({"type": "configure", "pool": "mono", "params": {f"k{i}": i for i in range(65)}}),
     "length <= 64"),
    (raw({"type": "configure", "pool": "mono", "params": {"bad key": 1}}), "matching regex"),
    (raw({"type": "configure", "pool": "mono"}), "missing required field `params`"),
    (raw({"type": "configure", "pool": "mono", "params": {"k": "x" * 5000}}), "at most"),
])
def test_configure_is_decoded_with_bounds(data: bytes, match: str) -> None:
    with pytest.raises(ProtocolError, match=match):
        messages.decode_configure(data)


def test_broker_names_a_pools_workers_for_new_parameters() -> None:
    b = broker()
    b.worker_ready(b"w1", "mono", 1, 0.0)
    b.worker_ready(b"w2", "mono", 1, 0.0)
    b.worker_ready(b"v1", "vo", 1, 0.0)
    assert sorted(b.pool_workers("mono")) == [b"w1", b"w2"]
    with pytest.raises(ValueError, match="no pool 'tags'"):
        b.pool_workers("tags")


@pytest.mark.parametrize(("text", "expected"), [
    ("conf=0.5", ("conf", 0.5)),
    ("n=3", ("n", 3)),
    ("debug=true", ("debug", True)),
    ("label=crab", ("label", "crab")),
    (" conf = 0.5", ("conf", 0.5)),
    ("empty=", ("empty", "")),
])
def test_param_assignment(text: str, expected: tuple[str, Any]) -> None:
    assert parse_assignment(text) == expected


@pytest.mark.parametrize(("text", "match"), [
    ("conf", "expected KEY=VALUE"),
    ("=3", "expected KEY=VALUE"),
    ("ids=[1, 2]", "a single value"),
    ("m={a: 1}", "a single value"),
])
def test_param_assignment_refused(text: str, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        parse_assignment(text)


def test_worker_gone_still_reaches_the_broker_for_a_retired_worker() -> None:
    s = core(count=2)
    s.pools.set_count("mono", 1, 1.0)
    acts = s.exited("worker:mono:1", 0, 2.0)
    assert isinstance(acts[0], WorkerGone)


# --- the commands: usage refused before anything is sent --------------------------------------


@pytest.mark.parametrize(("args", "code", "match"), [
    (["pool", "mono"], 2, "expected exactly one of"),
    (["pool", "mono", "--count", "2", "--deactivate"], 2, "--count, --deactivate"),
    (["pool", "mono", "--activate", "--deactivate"], 2, "--activate, --deactivate"),
    (["pool", "mono", "--count", "0"], 2, "0 is not in the range 1<=x<=64"),
    (["param", "mono", "conf"], 2, "expected KEY=VALUE"),
    (["param", "mono", "ids=[1, 2]"], 2, "a single value"),
    (["pool", "mono", "--count", "2"], 2, "no run directory"),  # nothing runs there
    (["param", "mono", "conf=0.5"], 2, "no run directory"),
])
def test_control_commands_refuse_bad_usage(tmp_path: Any, args: list[str], code: int,
                                           match: str) -> None:
    from click.testing import CliRunner

    from trapflow.cli import main as cli

    res = CliRunner().invoke(cli.main, [*args, "--run-dir", str(tmp_path / "none")])
    assert res.exit_code == code, res.output
    assert match in res.output


@pytest.mark.parametrize(("body", "expected", "match"), [
    (b'{"pool": "mono", "count": 2}', control_msgs.PoolRequest(pool="mono", count=2), None),
    (b'{"pool": "mono", "active": false}', control_msgs.PoolRequest(pool="mono", active=False),
     None),
    (b'{"pool": "mono", "policy": "fifo:4"}',
     control_msgs.PoolRequest(pool="mono", policy="fifo:4"), None),
    (b'{"pool": "mono"}', None, "exactly one of count, policy, active"),
    (b'{"pool": "mono", "count": 2, "active": true}', None, "exactly one"),
    (b'{"pool": "mono", "count": 0}', None, ">= 1"),
    (b'{"pool": "mo no", "count": 1}', None, "matching regex"),
    (b'{"count": 1}', None, "missing required field `pool`"),
    (b"not json", None, "pool change: JSON is malformed"),
    (b" " * 5000, None, "at most 4096 bytes"),
])
def test_viewer_pool_changes_are_decoded_with_bounds(
        body: bytes, expected: control_msgs.PoolRequest | None, match: str | None) -> None:
    """The viewer's page sends a pool change as JSON: the same bounds as the control socket."""
    if match is None:
        assert control_msgs.decode_pool_change(body) == expected
    else:
        with pytest.raises(ProtocolError, match=match):
            control_msgs.decode_pool_change(body)


def test_workers_added_later_get_the_pools_start_up_limit() -> None:
    """A worker a resize adds has supervisor.startup_timeout_s to become active, as the
    pool's first workers had (issue 27: 60 s was a constant, too short under emulation)."""
    s = SupervisorState((), Budget(max_restarts=2))
    s.pools.add_pool("mono", 1, "latest", {}, liveness_s=5.0, startup_s=600.0)
    assert kinds(s.pools.set_count("mono", 2, 1.0)) == ["AddWorker", "Spawn"]
    added = worker_name("mono", 1)
    assert s.nodes[added].plan.startup_s == 600.0
    s.spawned(added, 200, 1.0)
    assert s.start_problem([added], 500.0) is None
    assert s.start_problem([added], 602.0) is not None
