"""A recorded command frame replayed 3 times a second over the simulated acoustic link (two
pseudo-terminals and `modem-sim`), against a box with an hourly byte budget: data frames
keep reaching the surface, and a new command from the surface is answered.

Regression for issue 26 item 1: every replay of the last accepted command was answered with
its cached reply, before any data and without a rate limit, so one recorded `status` frame
replayed 3 times a second spent the hourly budget in about 30 s; the box then sent no data
and a new command got no reply.

The box here is the modem node's command path without a pipeline: the real sender
(trapflow.modem.sender), guard and schedule, with the status command answered in place of
the supervisor (as trapflow.modem.node dispatches the guard's decisions).
"""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import modem_link
from tests.integration.modem_writer import record
from trapflow.config.modem import ModemConfig, OutboxConfig
from trapflow.errors import unreachable
from trapflow.modem.command import CommandGuard, CounterState, Execute, Refuse, Reply
from trapflow.modem.frame import CMD_STATUS, REPLY_OK, Command
from trapflow.modem.outbox import Outbox
from trapflow.modem.sender import ModemSender
from trapflow.modem.surface import SurfaceReceiver
from trapflow.modem.surface_command import CommandClient

KEY = bytes(range(32))
BUDGET = 2000  # bytes per hour: the replays alone spent it in about 15 s before the fix
REPLAY_HZ = 3.0
REPLAY_S = 24.0
NEW_COMMAND_AT_S = 14.0  # after the old code had spent the budget on replays


class Box:
    """The sender and the command guard, stepped in the test's loop."""

    def __init__(self, outbox: Path, port: Path) -> None:
        cfg = ModemConfig(bit_rate=2400, ack_timeout_s=0.5, aggregate=[], ttl_s={},
                          housekeeping_s=0.05, bytes_per_hour=BUDGET)
        self.sender = ModemSender(outbox, str(port), cfg, OutboxConfig())
        self.guard = CommandGuard(KEY, self.sender.session,
                                  CounterState(session=self.sender.session.hex()))

    def step(self, now: float) -> None:
        self.sender.step(now)
        for payload in self.sender.take_commands():
            d = self.guard.receive(payload, now)
            if isinstance(d, Execute):
                reply, _ = self.guard.finished(d.counter, REPLY_OK, {"status": {"up": 1}})
                self.sender.send_reply(reply)
            elif isinstance(d, Reply):
                self.sender.send_reply(d.payload, d.repeat)
            elif not isinstance(d, Refuse):
                unreachable(d)


@pytest.mark.timeout(120)
def test_replays_do_not_stop_data_nor_a_new_command(
        tmp_path: Path, started_procs: list[subprocess.Popen[bytes]]) -> None:
    modem_link(tmp_path, started_procs, seed=26, bit_rate="2400", loss="0")
    outbox_path = tmp_path / "outbox.sqlite"
    writer = Outbox(outbox_path, OutboxConfig(fsync_interval_s=0.2))
    box = Box(outbox_path, tmp_path / "a")
    out_path = tmp_path / "surface.jsonl"
    out = out_path.open("wb")
    surface = SurfaceReceiver(str(tmp_path / "b"), out, reopen_interval_s=0.2,
                              fsync_interval_s=0.2)
    appended: dict[int, float] = {}  # record id -> seconds into the replays it was appended

    def run_until(done: Any, timeout: float, replay: bytes | None = None,
                  t0: float = 0.0, client: CommandClient | None = None) -> bool:
        """Step box and surface (replaying and appending from t0 on) until done() or timeout."""
        deadline = time.monotonic() + timeout
        next_replay = next_record = time.monotonic()
        while time.monotonic() < deadline:
            now = time.monotonic()
            box.step(now)
            surface.step()
            if replay is not None and now >= next_replay and surface.port.ensure_open():
                surface.port.write(replay)
                next_replay = now + 1 / REPLAY_HZ
            if replay is not None and now >= next_record:
                ident = 1000 + len(appended)
                writer.append(record(ident))
                appended[ident] = now - t0
                next_record = now + 1.0
            if client is not None:
                wire = client.due(now)
                if wire is not None and surface.port.ensure_open():
                    surface.port.write(wire)
            if done():
                return True
            time.sleep(0.01)
        return False

    def at_surface() -> set[int]:
        out.flush()
        return {next(iter(json.loads(line).values()))["seq"]
                for line in out_path.read_text().splitlines()}

    try:
        # A legitimate status command, answered; its frame is recorded by the attacker.
        first = CommandClient(KEY, tmp_path / "key.counter", box.sender.session,
                              Command(CMD_STATUS), retry_s=1.0)
        sent: list[bytes] = []
        due = first.due

        def recording_due(now: float) -> bytes | None:
            wire = due(now)
            if wire is not None:
                sent.append(wire)
            return wire

        first.due = recording_due  # type: ignore[method-assign]
        surface.on_reply = first.on_reply
        assert run_until(lambda: first.done, 20, client=first), first.outcome()
        assert first.ok and sent
        recorded = sent[0]

        # The replays begin, a record is appended every second, and a new command comes.
        t0 = time.monotonic()
        run_until(lambda: time.monotonic() - t0 >= NEW_COMMAND_AT_S, NEW_COMMAND_AT_S + 1,
                  replay=recorded, t0=t0)
        second = CommandClient(KEY, tmp_path / "key.counter", box.sender.session,
                               Command(CMD_STATUS), retry_s=1.0)
        surface.on_reply = second.on_reply
        answered = run_until(lambda: second.done, REPLAY_S - NEW_COMMAND_AT_S, replay=recorded,
                             t0=t0, client=second)
        waited = time.monotonic() - t0 - NEW_COMMAND_AT_S
        run_until(lambda: time.monotonic() - t0 >= REPLAY_S, REPLAY_S, replay=recorded, t0=t0)

        stats = box.sender.stats()
        counts = box.guard.counts
        print(f"sender: {stats}\nguard: {counts}")
        assert answered and second.ok, f"the new command got no reply: {second.outcome()}"
        assert waited < 5.0, f"the new command waited {waited:.1f} s for its reply"
        # Data kept flowing under the replays: the records appended in the last third of
        # the replays reached the surface (a record takes well under 2 s on this link).
        late = {i for i, t in appended.items() if REPLAY_S * 2 / 3 <= t <= REPLAY_S - 2}
        assert late and late <= at_surface(), f"missing: {sorted(late - at_surface())}"
        # The replays (duplicates of the last command, then stale once the new one ran)
        # were answered at most once per 5 s each, the rest held and counted, and the
        # repeats stayed within their share of the budget.
        replays = counts["duplicates"] + counts["refused_old"]
        assert replays >= REPLAY_S * REPLAY_HZ * 0.8
        assert stats["replies_repeated"] <= REPLAY_S / 5 + 2
        answers = stats["replies_repeated"] + stats.get("replies_over_share", 0)
        assert counts["replies_held"] + answers >= replays - 2  # a repeat already queued: once
        assert stats["repeat_bytes_last_hour"] <= BUDGET / 10
        assert stats["bytes_last_hour"] <= BUDGET
    finally:
        surface.close()
        out.close()
        box.sender.close()
        writer.close()
