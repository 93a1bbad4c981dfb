"""The broker's trust rules (trapflow.broker.trust), with no sockets: who may send what.

Pins the risk that control messages ride the workers' socket: any local worker could
stop a pool, change its policy, set the ladder's level, quiet the stop's warnings or
declare another worker dead, and a remote worker could do the same over the network,
unless every such message is checked against the supervisor's identity. These rules
lived as five checks spread through the broker's shell, testable only end to end
(tests/reliability/test_fuzz_sockets.py, tests/integration/test_recycle.py); a row per
sender and message here keeps a check from being lost when that shell changes.
"""

from __future__ import annotations

import pytest

from trapflow.broker import trust
from trapflow.broker.remote_state import RemoteWorkers
from trapflow.errors import ProtocolError
from trapflow.wire import control_msgs, messages

SUP = b"supervisor"  # the identity the supervisor's DEALER had before issue 26 item 9
W0 = b"vo:0:100"  # a local worker
W1 = b"vo:1:101"  # another local worker
R0 = b"vo@far:0:200"  # a remote worker that joined pool vo, started by OWNER
OWNER = b"far-supervisor"
STRANGER = b"vo@near:0:300"  # a remote identity that never said hello

READY = messages.Ready(worker="vo:0:100", pool="vo")
DONE = messages.Done(worker="vo:0:100", pool="vo", seq=1)
FAILED = messages.Failed(worker="vo:0:100", pool="vo", seq=1, reason="boom")
ALIVE = messages.Alive(worker="vo:0:100", pool="vo", free=1)
GONE_W0 = messages.Gone(worker="vo:0:100", reason="stopping")
GONE_R0 = messages.Gone(worker="vo@far:0:200", reason="stopping")
SWITCH = messages.PoolSwitch(pool="vo", active=False)
LEVEL = messages.LadderLevel(level="survival", reason="battery")
STOPPING = messages.Stopping()


def verdict(v: trust.Verdict) -> str:
    """"allow", or the refusal's reason."""
    return "allow" if isinstance(v, trust.Allow) else v.reason


@pytest.mark.parametrize(("sender", "msg", "expected"), [
    (W0, READY, "allow"),  # a worker's own traffic: the state checks answers, not trust
    (W1, DONE, "allow"),  # ...even naming another worker: BrokerState rejects the answer
    (W0, FAILED, "allow"),
    (W0, ALIVE, "allow"),
    (W0, GONE_W0, "allow"),  # a worker tells of its own end (a recycle, a stop)
    (W1, GONE_W0, "forged_gone"),  # a worker may not declare another dead
    # The supervisor's orders come on its own sealed channel: on this socket any process
    # of the same user could claim its old identity (issue 26 item 9), so nobody may.
    (SUP, GONE_W0, "forged_gone"),
    (SUP, STOPPING, "forged_stopping"),
    (W0, STOPPING, "forged_stopping"),  # it would quiet the warnings of a real failure
    (SUP, SWITCH, "forged_switch"),
    (W0, SWITCH, "forged_switch"),  # a worker could stop or reconfigure a pool
    (b"", SWITCH, "forged_switch"),  # an empty identity is nobody's
    (SUP, LEVEL, "forged_level"),
    (W0, LEVEL, "forged_level"),  # the ladder's level in the stats is the supervisor's
])
def test_who_may_send_what_on_the_workers_socket(
        sender: bytes, msg: trust.LocalMsg, expected: str) -> None:
    assert verdict(trust.on_workers_socket(sender, msg)) == expected


KEY = bytes(range(control_msgs.ORDER_KEY_BYTES))
OTHER_KEY = bytes(control_msgs.ORDER_KEY_BYTES)


def _tampered() -> list[bytes]:
    seal, body = control_msgs.seal_order(KEY, SWITCH)
    return [seal, body.replace(b"vo", b"vp")]


@pytest.mark.parametrize(("frames", "error"), [
    (control_msgs.seal_order(OTHER_KEY, SWITCH), "its seal is not the run's"),  # a guess
    (_tampered(), "its seal is not the run's"),  # a real order, altered on the way
    ([b"x" * 32, messages.encode(SWITCH)], "its seal is not the run's"),
    ([messages.encode(SWITCH)], "expected 2 frames"),  # the old, unsealed order
    (control_msgs.seal_order(KEY, SWITCH) + [b""], "expected 2 frames"),
    ([control_msgs.seal_order(KEY, SWITCH)[0][:31], messages.encode(SWITCH)], "its seal"),
    # Sealed, but no order: a worker's message is never the supervisor's to send here.
    ([*control_msgs.seal_order(KEY, READY)], "supervisor order"),  # type: ignore[arg-type]
])
def test_only_orders_sealed_with_the_runs_key_are_opened(frames: list[bytes], error: str
                                                          ) -> None:
    """Pins issue 26 item 9: the supervisor's orders were taken from whoever claimed its
    identity on the workers socket."""
    with pytest.raises(ProtocolError, match=error):
        control_msgs.open_order(KEY, frames)


@pytest.mark.parametrize("order", [SWITCH, LEVEL, STOPPING, GONE_W0])
def test_a_sealed_order_opens_as_sent(order: control_msgs.SupervisorOrder) -> None:
    assert control_msgs.open_order(KEY, control_msgs.seal_order(KEY, order)) == order
    with pytest.raises(ProtocolError):  # an empty key (a broker spawned without one)
        control_msgs.open_order(b"", control_msgs.seal_order(b"", order))


@pytest.mark.parametrize(("msg", "expected"), [
    (READY, "vo:0:100"),  # a worker's first message names its link
    (GONE_W0, "vo:0:100"),  # a goodbye as the first message still names the worker
    (SWITCH, "malformed"),  # the supervisor is never on a link: no worker opens with these
    (LEVEL, "malformed"),
    (STOPPING, "malformed"),
])
def test_what_a_local_link_may_open_with(msg: trust.LocalMsg, expected: str) -> None:
    named = trust.names_link(msg)
    assert (named.reason if isinstance(named, trust.Refuse) else named) == expected


def _roster() -> RemoteWorkers:
    roster = RemoteWorkers()
    roster.joined(R0, "far", "vo", OWNER, 0.0)
    return roster


@pytest.mark.parametrize(("sender", "msg", "expected"), [
    # joining: the pool's config decides the welcome, not trust
    (STRANGER, messages.JoinRequest(pool="vo", host="near"), "allow"),
    (STRANGER, messages.Hello(worker="vo@near:0:300", pool="vo", host="near", owner="o"),
     "allow"),
    (OWNER, messages.HostAlive(host="far"), "allow"),  # heartbeats of unknown owners: ignored
    # a joined worker's traffic, for its own pool only
    (R0, messages.Ready(worker="vo@far:0:200", pool="vo"), "allow"),
    (R0, messages.Done(worker="vo@far:0:200", pool="vo", seq=1), "allow"),
    (R0, messages.Ready(worker="vo@far:0:200", pool="ir"), "remote_not_joined"),  # other pool
    (STRANGER, messages.Alive(worker="vo@near:0:300", pool="vo"), "remote_not_joined"),
    (R0, SWITCH, "allow"),  # joined vo; the workers' rule then refuses it (forged_switch)
    (STRANGER, SWITCH, "remote_not_joined"),
    # deaths: the worker itself or the supervisor that started it, never another
    (R0, GONE_R0, "allow"),
    (OWNER, GONE_R0, "allow"),
    (STRANGER, GONE_R0, "forged_gone"),
    (SUP, GONE_R0, "forged_gone"),  # "supervisor" on the remote socket is not ours
    (R0, GONE_W0, "forged_gone"),  # a local worker's death is not a remote's to tell
    # the supervisor's notices never come from another host
    (R0, LEVEL, "forged_level"),
    (SUP, LEVEL, "forged_level"),
    (R0, STOPPING, "forged_stopping"),
    (SUP, STOPPING, "forged_stopping"),
])
def test_who_may_send_what_on_the_remote_socket(
        sender: bytes, msg: messages.WorkerMsg, expected: str) -> None:
    assert verdict(trust.on_remote_socket(sender, msg, _roster())) == expected


def test_a_remote_pool_switch_is_then_refused_as_on_the_workers_socket() -> None:
    """A joined remote worker's pool switch passes the remote rule (it names its own pool)
    and is refused by the workers' rule that follows: never applied, counted once."""
    assert verdict(trust.on_remote_socket(R0, SWITCH, _roster())) == "allow"
    assert verdict(trust.on_workers_socket(R0, SWITCH)) == "forged_switch"


def test_a_refusal_names_the_sender_escaped() -> None:
    """The log line carries wire names escaped: a forged identity cannot forge a line."""
    v = trust.on_workers_socket(b"evil\nINFO fake", SWITCH)
    assert isinstance(v, trust.Refuse)
    assert "\n" not in v.text() and "evil\\nINFO fake" in v.text()
