"""What the normalizer tells the gate, pure: the rig moves or is still (VO, hysteresis), when
a hint is sent, and the hint's decoding on the broker's side."""

from __future__ import annotations

import math

import pytest

from trapflow.errors import ProtocolError
from trapflow.gate.hint import HintPacer, RigConfig, RigMotion, rotation_deg
from trapflow.wire import gate_msgs, messages

I3 = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
DT = 0.1  # 10 pairs/s


def yaw(deg: float) -> tuple[float, ...]:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return (c, 0.0, s, 0.0, 1.0, 0.0, -s, 0.0, c)


def step(m_s: float = 0.0, deg_s: float = 0.0, ok: bool = True) -> tuple[bool, tuple[float, ...],
                                                                         tuple[float, ...]]:
    """One VO result at 10 pairs/s moving at this speed and turn rate."""
    return ok, yaw(deg_s * DT) if deg_s else I3, (0.0, 0.0, m_s * DT)


def play(rig: RigMotion, steps: list[tuple[bool, tuple[float, ...], tuple[float, ...]]]
         ) -> list[tuple[int, bool]]:
    out = []
    for i, (ok, r, t) in enumerate(steps):
        got = rig.vo(i * DT, ok, r, t)
        if got is not None:
            out.append((i, got))
    return out


STILL, SLOW = step(), step(m_s=0.01)
FAST, TURN = step(m_s=0.2), step(deg_s=10.0)


@pytest.mark.parametrize(("steps", "want"), [
    # A static rig (VO noise well under the thresholds): never moving.
    ([STILL, SLOW] * 50, []),
    # 3 results in a row past the speed threshold: moving (at the 4th result: the first
    # only marks the time).
    ([STILL] + [FAST] * 5, [(3, True)]),
    # Turning counts as moving too.
    ([STILL] + [TURN] * 5, [(3, True)]),
    # A single fast result (noise, a fish filling the view) is not a moving rig.
    ([STILL, FAST, STILL, FAST, FAST, STILL] * 5, []),
    # Still again only after 2 s below half the thresholds (20 results after the first).
    ([STILL] + [FAST] * 3 + [STILL] * 25, [(3, True), (24, False)]),
    # Between half and the threshold (3 cm/s): neither, the rig stays moving.
    ([STILL] + [FAST] * 3 + [step(m_s=0.03)] * 40, [(3, True)]),
    # Failed VO results say nothing (a fast rig blurs: they neither count nor break a run).
    ([STILL] + [FAST, step(m_s=0.2, ok=False)] * 5, [(5, True)]),
    ([STILL] + [step(m_s=0.2, ok=False)] * 20, []),
])
def test_rig_motion(steps: list[tuple[bool, tuple[float, ...], tuple[float, ...]]],
                    want: list[tuple[int, bool]]) -> None:
    assert play(RigMotion(RigConfig()), steps) == want


def test_rotation_angle() -> None:
    assert rotation_deg(I3) == 0.0
    assert rotation_deg(yaw(30.0)) == pytest.approx(30.0)


@pytest.mark.parametrize(("said", "want"), [
    # (tracks, rig moving, t): sent on a change, again every second while either holds.
    ([(0, False, 0.0), (0, False, 5.0)], [True, False]),
    ([(0, False, 0.0), (2, False, 0.1), (3, False, 0.5), (3, False, 1.1), (0, False, 1.2)],
     [True, True, False, True, True]),
    ([(0, True, 0.0), (0, True, 0.9), (0, True, 1.0), (0, False, 1.1)],
     [True, False, True, True]),
])
def test_hint_pacing(said: list[tuple[int, bool, float]], want: list[bool]) -> None:
    pacer = HintPacer()
    assert [pacer.due(n, moving, t) for n, moving, t in said] == want


def test_a_new_broker_hears_it_again() -> None:
    pacer = HintPacer()
    assert pacer.due(0, False, 0.0)
    pacer.forget()
    assert pacer.due(0, False, 0.1)


@pytest.mark.parametrize(("msg", "error"), [
    (gate_msgs.GateHint(tracks=3, rig_moving=True), None),
    (messages.ResultsAck(count=4), None),
    (messages.ResultsAck(count=-1), "results ack: expected a count >= 0, got -1"),
    (gate_msgs.GateHint(tracks=-1), "normalizer message: Expected `int` >= 0"),
    (messages.Ready(worker="w", pool="p", credit=1), "normalizer message: Invalid value 'ready'"),
])
def test_normalizer_msg_decoding(msg: messages.Msg, error: str | None) -> None:
    data = messages.encode(msg)
    if error is None:
        assert gate_msgs.decode_normalizer_msg(data) == msg
    else:
        with pytest.raises(ProtocolError, match=error):
            gate_msgs.decode_normalizer_msg(data)
