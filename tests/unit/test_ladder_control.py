"""The ladder applied, without processes: the supervision core turns level changes into pool
switches (and keeps the operator's deactivations), the broker gives a pool at most one pair
per minimum interval (the rest counted throttled), the ledger counts those as dropped by the
level, and the sensors read files in their units, a missing one as a missing reading."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import pytest

from trapflow.broker.state import BrokerState, Dispatch, PoolSpec, Release
from trapflow.config.ladder import AUTO, LadderConfig, SensorsConfig, TriggerConfig
from trapflow.config.schema import parse_policy
from trapflow.runtime.lifecycle import Lifecycle
from trapflow.supervisor.actions import Budget, LevelChanged, Refused, SwitchPool
from trapflow.supervisor.ladder import Ladder, Readings
from trapflow.supervisor.ledger import RunLedger
from trapflow.supervisor.sensors import Sensors
from trapflow.supervisor.state import SupervisorState
from trapflow.wire import control_msgs, messages

HOT = TriggerConfig(sensor="cpu_temp_c", dwell_s=0.0,
                    enter={"ir_slowed": 75, "mono_vo": 80, "vo_health": 85},
                    release={"ir_slowed": 70, "mono_vo": 75, "vo_health": 80})


def core(*pools: str) -> SupervisorState:
    s = SupervisorState((), Budget(), ladder=Ladder(LadderConfig(triggers=[HOT])))
    for name in pools or ("mono", "stereo", "vo"):
        s.pools.add_pool(name, 1, "latest", {}, liveness_s=5.0)
    return s


def hot(s: SupervisorState, temp: float, now: float) -> list[Any]:
    return s.pools.degrade(Readings(cpu_temp_c=temp), now)


# --- the supervision core ---------------------------------------------------------------------


@pytest.mark.parametrize(("temps", "level", "switches"), [
    # full -> ir_slowed: the stereo recogniser gets one pair per 5 s
    ([76], "ir_slowed", [SwitchPool("stereo", min_interval_s=5.0)]),
    # -> mono_vo: stereo off (and its interval back to none); tags is not in this run
    ([90, 90], "mono_vo", [SwitchPool("stereo", active=False, min_interval_s=0.0)]),
    # -> vo_health: mono off too
    ([90, 90, 90], "vo_health", [SwitchPool("mono", active=False)]),
    # back down to mono_vo: mono on again, stereo stays off
    ([90, 90, 90, 79], "mono_vo", [SwitchPool("mono", active=True)]),
])
def test_level_changes_become_pool_switches(temps: list[float], level: str,
                                            switches: list[SwitchPool]) -> None:
    s = core()
    acts: list[Any] = []
    for i, t in enumerate(temps):
        acts = hot(s, t, float(i))
    assert acts[:-1] == switches
    assert acts[-1] == LevelChanged(level, s.pools.ladder.reason if s.pools.ladder else "", False)
    assert s.timeline[-1].kind == "level" and s.timeline[-1].node == "ladder"
    assert s.counts()["level"] == len(temps)


def test_no_change_no_actions() -> None:
    s = core()
    assert hot(s, 40, 0.0) == []
    hot(s, 76, 1.0)
    assert hot(s, 72, 2.0) == []  # held by hysteresis


def test_the_ladder_never_activates_a_pool_the_operator_deactivated() -> None:
    s = core()
    s.pools.set_active("mono", False, 0.0)  # the operator
    hot(s, 90, 1.0)
    hot(s, 90, 2.0)
    acts = hot(s, 90, 3.0)  # vo_health: mono is off already, by the operator
    assert not any(isinstance(a, SwitchPool) and a.pool == "mono" for a in acts)
    for t in range(4, 8):
        acts = hot(s, 40, float(t))  # all the way back to full
        assert not any(isinstance(a, SwitchPool) and a.pool == "mono" and a.active
                       for a in acts)
    assert s.pools.ladder is not None and s.pools.ladder.level == "full"
    assert s.pools.by_name["mono"].state == Lifecycle.INACTIVE
    assert s.pools.pool_view()["mono"]["off_by"] == "operator"
    assert s.pools.by_name["stereo"].state == Lifecycle.ACTIVE  # the ladder's own: back on


def test_the_operator_takes_over_a_pool_the_ladder_switched_off() -> None:
    s = core()
    hot(s, 90, 0.0)
    hot(s, 90, 1.0)  # mono_vo: stereo off by the ladder
    assert s.pools.set_active("stereo", False, 2.0) == []  # off already: nothing to tell
    assert s.pools.pool_view()["stereo"]["off_by"] == "operator"
    assert s.timeline[-1].kind == "control"
    for t in range(3, 6):
        acts = hot(s, 40, float(t))
        assert not any(isinstance(a, SwitchPool) and a.pool == "stereo" and a.active
                       for a in acts)
    assert s.pools.ladder is not None and s.pools.ladder.level == "full"
    assert s.pools.by_name["stereo"].state == Lifecycle.INACTIVE
    with pytest.raises(Refused, match="is inactive"):
        s.pools.set_active("stereo", False, 6.0)  # the operator's own: no transition


def test_an_operator_activation_holds_until_the_next_level_change() -> None:
    s = core()
    hot(s, 90, 0.0)
    hot(s, 90, 1.0)  # mono_vo: stereo off by the ladder
    assert s.pools.pool_view()["stereo"]["off_by"] == "ladder"
    assert s.pools.set_active("stereo", True, 2.0) == [SwitchPool("stereo", active=True)]
    assert hot(s, 79, 3.0) == []  # same level: the operator's choice stands
    acts = hot(s, 90, 4.0)  # vo_health: a new level switches it off again
    assert SwitchPool("stereo", active=False) in acts


def test_force_and_auto() -> None:
    s = core()
    acts = s.pools.force_level("mono_vo", 0.0)
    assert acts[-1] == LevelChanged("mono_vo", "full -> mono_vo: forced by the operator", True)
    assert SwitchPool("stereo", active=False) in acts
    assert hot(s, 40, 1.0) == []  # forced: the cold reading changes nothing
    assert s.pools.force_level(AUTO, 2.0) == []
    assert s.timeline[-1].reason == "mono_vo: auto (from mono_vo)"
    assert [type(a).__name__ for a in hot(s, 40, 3.0)][-1] == "LevelChanged"
    with pytest.raises(Refused, match="expected one of full"):
        s.pools.force_level("boiling", 4.0)


def test_no_ladder_refuses_a_level_and_never_degrades() -> None:
    s = SupervisorState((), Budget())
    with pytest.raises(Refused, match="ladder.enabled: false"):
        s.pools.force_level("full", 0.0)
    assert s.pools.degrade(Readings(cpu_temp_c=99), 0.0) == []
    assert s.pools.ladder_view() is None


# --- the broker: one pair per minimum interval ------------------------------------------------


def broker() -> BrokerState:
    return BrokerState({"stereo": PoolSpec(parse_policy("latest"), 10.0),
                        "vo": PoolSpec(parse_policy("fifo:64"), 10.0)})


def test_min_interval_dispatches_one_pair_per_interval_and_counts_the_rest() -> None:
    b = broker()
    b.set_interval("stereo", 1.0, 0.0)
    b.worker_ready(b"w", "stereo", 1, 0.0)
    sent = []
    for i in range(40):  # 10 pairs/s for 4 s; the worker answers at once
        now = i * 0.1
        for a in b.pair_arrived(i, now):
            if isinstance(a, Dispatch) and a.pool == "stereo":
                sent.append(i)
                b.job_done(b"w", "stereo", i, True, now)
    assert sent == [0, 10, 20, 30]
    st = b.pool_stats()["stereo"]
    assert (st.processed, st.throttled, st.dropped, st.min_interval_s) == (4, 36, 0, 1.0)
    assert st.received == st.processed + st.throttled  # every pair in exactly one state
    assert b.pool_stats()["vo"].throttled == 0


def test_min_interval_drops_what_waits_when_one_goes() -> None:
    b = BrokerState({"stereo": PoolSpec(parse_policy("fifo:8"), 10.0)})
    for seq in range(3):
        b.pair_arrived(seq, 0.0)  # no worker yet: pending
    b.set_interval("stereo", 5.0, 0.0)
    acts = b.worker_ready(b"w", "stereo", 1, 0.1)
    assert acts[0] == Dispatch(b"w", "stereo", 0, 0)
    assert Release(1) in acts and Release(2) in acts
    st = b.pool_stats()["stereo"]
    assert (st.pending, st.throttled) == (0, 2)


def test_min_interval_off_again() -> None:
    b = broker()
    b.worker_ready(b"w", "stereo", 5, 0.0)
    b.set_interval("stereo", 100.0, 0.0)
    b.pair_arrived(0, 0.0)
    assert not any(isinstance(a, Dispatch) and a.pool == "stereo"
                   for a in b.pair_arrived(1, 1.0))
    b.set_interval("stereo", 0.0, 2.0)
    assert any(isinstance(a, Dispatch) and a.pool == "stereo" for a in b.pair_arrived(2, 2.0))
    with pytest.raises(ValueError, match="expected a minimum interval >= 0"):
        b.set_interval("stereo", -1.0, 3.0)
    with pytest.raises(ValueError, match="no pool 'tags'"):
        b.set_interval("tags", 1.0, 3.0)


def test_latency_is_arrival_to_answer() -> None:
    b = broker()
    b.worker_ready(b"w", "stereo", 1, 0.0)
    b.pair_arrived(0, 1.0)
    b.job_done(b"w", "stereo", 0, True, 1.5)
    assert b.pool_stats()["stereo"].latency_ms == 500.0


def test_ledger_counts_throttled_pairs_as_dropped_by_the_level() -> None:
    led = RunLedger()
    led.on_stats(messages.Stats(t_wall_ns=0, uptime_s=1.0, pairs_in=10, rate_in=10.0,
                                malformed=0, level="ir_slowed", pools={
                                    "stereo": messages.PoolStats(received=10, processed=2,
                                                                 throttled=8)}))
    pool = led.ledger({"stereo": "latest"}, {})["pools"]["stereo"]
    assert (pool["processed"], pool["dropped_by_level"], pool["lost"]) == (2, 8, 0)
    line = led.status_text(1.0, {}, level="ir_slowed")
    assert "[ir_slowed]" in line and "drop 8" in line


@pytest.mark.parametrize("msg", [
    messages.PoolSwitch(pool="stereo", min_interval_s=5.0),
    messages.LadderLevel(level="ir_slowed", reason="full -> ir_slowed: cpu_temp_c 85C"),
])
def test_ladder_messages_on_the_worker_socket(msg: messages.Msg) -> None:
    assert messages.decode_worker_msg(messages.encode(msg)) == msg


def test_level_request_round_trips() -> None:
    req = control_msgs.LevelRequest(level="auto")
    assert control_msgs.decode_control(messages.encode(req)) == req


# --- the sensors ----------------------------------------------------------------------------


@pytest.mark.parametrize(("text", "unit", "expected"), [
    ("85000\n", "mC", 85.0),
    ("41.5", "C", 41.5),
])
def test_temperature_file_in_its_unit(tmp_path: Path, text: str, unit: str,
                                      expected: float) -> None:
    f = tmp_path / "temp"
    f.write_text(text)
    s = Sensors(SensorsConfig(temperature_path=str(f), temperature_unit=unit), tmp_path)
    assert s.read().cpu_temp_c == pytest.approx(expected)


@pytest.mark.parametrize(("text", "unit", "expected"), [
    ("12150000", "uV", 12.15),
    ("12150", "mV", 12.15),
    ("12.15", "V", 12.15),
])
def test_battery_file_in_its_unit(tmp_path: Path, text: str, unit: str,
                                  expected: float) -> None:
    f = tmp_path / "voltage_now"
    f.write_text(text)
    s = Sensors(SensorsConfig(temperature_path="", battery_path=str(f), battery_unit=unit),
                tmp_path)
    assert s.read().battery_v == pytest.approx(expected)


@pytest.mark.parametrize("content", [None, "", "hot", "1" * 100, b"\xff\xfe"])
def test_unreadable_sensor_is_missing_and_named_once(tmp_path: Path, content: Any,
                                                     caplog: pytest.LogCaptureFixture) -> None:
    f = tmp_path / "temp"
    if isinstance(content, bytes):
        f.write_bytes(content)
    elif content is not None:
        f.write_text(content)
    s = Sensors(SensorsConfig(temperature_path=str(f)), tmp_path)
    with caplog.at_level(logging.INFO, logger="trapflow.supervisor.sensors"):
        readings = [s.read() for _ in range(3)]
    assert all(r.cpu_temp_c is None for r in readings)
    named = [r for r in caplog.records if "temperature sensor" in r.getMessage()]
    assert len(named) == 1 and str(f) in named[0].getMessage()


def test_disk_load_and_pools(tmp_path: Path) -> None:
    stats = messages.Stats(t_wall_ns=0, uptime_s=1.0, pairs_in=1, rate_in=1.0, malformed=0,
                           pools={"stereo": messages.PoolStats(pending=3, latency_ms=250.0),
                                  "vo": messages.PoolStats()})
    r = Sensors(SensorsConfig(temperature_path=""), tmp_path).read(stats, outbox_backlog=7)
    assert r.disk_free_mb is not None and r.disk_free_mb > 0
    assert r.disk_free_pct is not None and 0 < r.disk_free_pct <= 100
    assert r.load_per_core == pytest.approx(os.getloadavg()[0] / (os.cpu_count() or 1),
                                            abs=1.0)
    assert r.pool_backlog == {"stereo": 3.0, "vo": 0.0}
    assert r.pool_latency_ms == {"stereo": 250.0}  # vo: nothing processed, no latency
    assert r.outbox_backlog == 7.0 and r.cpu_temp_c is None and r.battery_v is None


def test_level_cli_refuses_without_a_pipeline(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from trapflow.cli import main as cli

    res = CliRunner().invoke(cli.main, ["level", "auto", "--run-dir", str(tmp_path / "none")])
    assert res.exit_code == 2, res.output
    assert "no run directory" in res.output
