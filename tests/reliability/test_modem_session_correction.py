"""An old command frame replayed over the simulated acoustic link (two pseudo-terminals and
`modem-sim`) while the surface sends a command without `--session`: the box's session
correction still reaches the surface, and the command is answered promptly.

Regression for issue 26 item 7: stale and wrong-session answers shared one slot per 5 s, so
an old frame replayed once a second took it each time it opened, and a surface command
that takes about a second timed out after 60 s. The box here is the modem node's command
path without a pipeline (tests/reliability/test_modem_replay_budget.py's Box).
"""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import pytest

from tests.conftest import modem_link
from tests.reliability.test_modem_replay_budget import KEY, Box
from trapflow.modem.frame import CMD_STATUS, Command
from trapflow.modem.surface import SurfaceReceiver
from trapflow.modem.surface_command import CommandClient

REPLAY_HZ = 3.0  # the once a second, and faster: the old slot was taken sooner
OLD_SESSION = bytes.fromhex("0badf00d")  # a session this box never had: a recorded frame
PROMPT_S = 12.0  # one exchange takes about a second; the surface retries 8 s apart


@pytest.mark.timeout(120)
def test_a_command_without_session_is_corrected_while_an_old_frame_is_replayed(
        tmp_path: Path, started_procs: list[subprocess.Popen[bytes]]) -> None:
    modem_link(tmp_path, started_procs, seed=7, bit_rate="2400", loss="0")
    box = Box(tmp_path / "outbox.sqlite", tmp_path / "a")
    out = (tmp_path / "surface.jsonl").open("wb")
    surface = SurfaceReceiver(str(tmp_path / "b"), out, reopen_interval_s=0.2,
                              fsync_interval_s=0.2)
    try:
        # The attacker's frame: genuine (signed with the key), but for an old session.
        # Another counter than the surface's: the box's answers to it are not the surface's.
        (tmp_path / "old.counter").write_text('{"next": 500}\n')
        old = CommandClient(KEY, tmp_path / "old.counter", OLD_SESSION, Command(CMD_STATUS))
        recorded = old.due(time.monotonic())
        assert recorded is not None
        # The surface knows no session (no --session, nothing heard): it sends to 00000000
        # and follows the box's correction.
        client = CommandClient(KEY, tmp_path / "key.counter", bytes(4), Command(CMD_STATUS))
        surface.on_reply = client.on_reply
        t0 = time.monotonic()
        next_replay = t0
        client_from = None  # the replays run first, as in the issue: until one is held
        answered_at = None
        while time.monotonic() - t0 < PROMPT_S + 20.0:
            now = time.monotonic()
            if client_from is None and box.guard.counts.get("replies_held"):
                client_from = now  # the old frame was answered, and replayed again
            box.step(now)
            surface.step()
            if now >= next_replay and surface.port.ensure_open():
                surface.port.write(recorded)
                next_replay = now + 1 / REPLAY_HZ
            if client_from is not None and not client.done:
                wire = client.due(now)
                if wire is not None and surface.port.ensure_open():
                    surface.port.write(wire)
            if client.done and client_from is not None:
                answered_at = now - client_from
                break
            time.sleep(0.01)
        counts = box.guard.counts
        print(f"guard: {counts}\nclient: {client.outcome()}")
        assert answered_at is not None and client.ok, f"no answer: {client.outcome()}"
        assert answered_at < PROMPT_S, f"the command waited {answered_at:.1f} s"
        assert client.counts["corrections"] == 1  # corrected to the box's session once
        # The replays were refused and mostly held: one answer per 5 s for that frame.
        replays = counts["refused_session"] - 1  # the surface's first frame was one too
        assert replays >= answered_at * REPLAY_HZ * 0.7, counts
        assert counts["replies_held"] >= replays - (now - t0) / 5 - 2, counts
    finally:
        surface.close()
        out.close()
        box.sender.close()
