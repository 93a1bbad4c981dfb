"""Signed commands from the surface to a real running pipeline over the simulated lossy
acoustic link: `trapflow surface --command` changes a pool once however often the frame
travels, a retransmission gets the cached reply, status and a health record come back
signed, a replayed older frame and a forged frame are refused and counted by the box's
modem node."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import REPO, Pipeline, modem_cli, only_pools, poll_for, write_config
from trapflow.modem.command import parse_reply_body, sign, verify
from trapflow.modem.frame import (
    CMD_HEALTH,
    CMD_LEVEL,
    CMD_POOL_COUNT,
    CMD_STATUS,
    COMMAND,
    REPLY,
    REPLY_OK,
    Command,
    command_body,
    frame,
    split_signed,
)
from trapflow.modem.surface import SurfaceReceiver
from trapflow.modem.surface_command import CommandClient
from trapflow.wire.control_client import request

pytestmark = pytest.mark.slow  # starts whole pipelines


def status(p: Pipeline) -> dict[str, Any]:
    """The status straight from the control socket (no interpreter start per call)."""
    return request(p.run_dir, "status", timeout_s=10)


def modem_counters(p: Pipeline) -> dict[str, int]:
    node = next(n for n in status(p)["nodes"] if n["name"] == "modem")
    counters: dict[str, int] = node["counters"]
    return counters


def control_changes(p: Pipeline) -> list[dict[str, Any]]:
    return [e for e in status(p)["supervision"]["timeline"] if e["kind"] == "control"]


@pytest.mark.timeout(240)
def test_commands_run_once_replays_and_forgeries_are_refused(
        spawn, run_dir: Path, started_procs: list[subprocess.Popen[bytes]]) -> None:
    link = run_dir.parent
    started_procs.append(modem_cli(
        "modem-sim", "--bit-rate", "9600", "--latency", "0.05", "--loss", "0.25",
        "--seed", "5", "--link-a", str(link / "a"), "--link-b", str(link / "b")))
    poll_for(lambda: (link / "a").exists() and (link / "b").exists(), 20, what="the ptys")
    key_path = link / "key"
    key = os.urandom(32)
    key_path.write_bytes(key)
    key_path.chmod(0o600)
    cfg = write_config(link / "cmd.yaml", {
        "source": {"width": 160, "height": 120, "rate_hz": 4.0},
        "pools": only_pools({"stereo": {"plugin": "noop", "policy": "latest",
                                        "gate": "always"}}),
        "modem": {"enabled": True, "port": str(link / "a"), "bit_rate": 9600.0,
                  "ack_timeout_s": 1.0, "reopen_interval_s": 0.5,
                  "command_key": str(key_path)},
        "health": {"enabled": False},
    })
    p: Pipeline = spawn(["--config", str(cfg)], run_dir)
    p.wait_active()

    # 1. The command line: grows the pool; the reply says what changed.
    res = subprocess.run(
        [sys.executable, "-m", "trapflow", "surface", str(link / "b"), "--command",
         "pool stereo --count 2", "--key", str(key_path), "--retry", "0.6", "--timeout", "60"],
        capture_output=True, text=True, timeout=80, cwd=REPO, check=False)
    assert res.returncode == 0, res.stderr
    reply = json.loads(res.stdout)
    assert reply["reply"] == "ok" and reply["changed"] == "pool:stereo", reply
    assert "count 1 -> 2" in reply["change"]
    counter, session = reply["counter"], bytes.fromhex(reply["session"])
    first = frame(COMMAND, sign(key, COMMAND, session, counter,
                                command_body(Command(CMD_POOL_COUNT, "stereo", count=2))))

    replies: list[bytes] = []
    surface = SurfaceReceiver(str(link / "b"), None, on_reply=replies.append,
                              reopen_interval_s=0.2)

    def send_until(wire: bytes, done: Any, what: str, timeout: float = 15) -> Any:
        """Send the frame again every 0.4 s (the link loses some) until done() holds."""
        deadline = time.monotonic() + timeout
        next_send = 0.0
        while time.monotonic() < deadline:
            surface.step()
            if time.monotonic() >= next_send and surface.port.ensure_open():
                surface.port.write(wire)
                next_send = time.monotonic() + 0.4
            got = done()
            if got:
                return got
            surface.port.wait_readable(0.05)
        raise AssertionError(f"timed out waiting for {what}")

    try:
        # 2. The same frame again (a retransmission): the cached reply, not a second run.
        def cached() -> dict[str, Any] | None:
            for payload in replies:
                f = split_signed(REPLY, payload)
                if f.counter == counter and verify(key, f):
                    return parse_reply_body(f.body)[1]
            return None

        # The box answers a repeat at most once per REPEAT_REPLY_INTERVAL_S (5 s), and the
        # link loses a quarter of the frames each way: several chances need tens of seconds.
        again = send_until(first, cached, "the cached reply", timeout=45)
        assert again == {"changed": "pool:stereo", "change": reply["change"]}

        def run_command(cmd: Command) -> dict[str, Any]:
            """One command through the library client (as the command line runs it)."""
            client = CommandClient(key, key_path.with_name("key.counter"), session, cmd,
                                   retry_s=0.6)
            surface.on_reply = client.on_reply
            deadline = time.monotonic() + 60  # a lost reply is repeated once per 5 s
            while not client.done and time.monotonic() < deadline:
                surface.step()
                wire = client.due(time.monotonic())
                if wire is not None and surface.port.ensure_open():
                    surface.port.write(wire)
                surface.port.wait_readable(0.05)
            assert client.ok, client.outcome()
            assert client.result is not None and client.result[0] == REPLY_OK
            return client.outcome()

        # 3. Status and a health record now: the pool has 2 workers.
        st = run_command(Command(CMD_STATUS))
        assert st["counter"] == counter + 1
        assert st["pools"]["stereo"][:2] == ["active", 2]  # state, workers
        health = run_command(Command(CMD_HEALTH))["health"]
        assert health["disk_free_mb"] > 0 and health["link"] == "active"
        # The degradation ladder forced from the surface: stereo off at mono_vo.
        lv = run_command(Command(CMD_LEVEL, text="mono_vo"))
        assert (lv["level"], lv["auto"]) == ("mono_vo", False), lv
        assert lv["reason"] == "full -> mono_vo: forced by the operator"
        assert run_command(Command(CMD_STATUS))["status"]["level"] == "mono_vo"
        assert status(p)["supervision"]["pools"]["stereo"]["off_by"] == "ladder"

        # 4. The first frame once more: now older than the last accepted, refused.
        surface.on_reply = replies.append
        send_until(first, lambda: modem_counters(p).get("commands_refused_old", 0) >= 1,
                   "the replayed frame refused")
        # 5. A forged frame (another key) with a fresh counter: refused, never answered.
        forged = frame(COMMAND, sign(os.urandom(32), COMMAND, session, counter + 10,
                                     command_body(Command(CMD_POOL_COUNT, "stereo", count=3))))
        send_until(forged, lambda: modem_counters(p).get("commands_refused_tag", 0) >= 1,
                   "the forged frame refused")
    finally:
        surface.close()

    counters = modem_counters(p)
    assert counters["commands_accepted"] == 5  # pool change, status, health, level, status
    assert counters["commands_duplicates"] >= 1
    assert counters["replies"] >= 3
    changes = control_changes(p)
    assert len(changes) == 1 and changes[0]["node"] == "pool:stereo", changes
    assert status(p)["supervision"]["pools"]["stereo"]["count"] == 2
    code, _out, err = p.stop()
    assert code == 0, err
    assert "surface command refused" in (run_dir / "trapflow.log").read_text()
