"""A fresh outbox against a surface that stayed up: the box is restarted with a new run
directory (or its outbox deleted) while `trapflow surface` and the link keep running.

Real processes: the link simulator, the surface receiver and the box's sender
(`modem-send`), over pseudo-terminals. The new outbox numbers its records from 1 again;
every one of them must reach the surface exactly once.
"""

from __future__ import annotations

import json
import signal
import subprocess
from pathlib import Path

import pytest

from tests.conftest import modem_cli, poll_for
from tests.integration.modem_writer import record
from trapflow.modem.outbox import Outbox, OutboxConfig, OutboxQueue

SEED = 20261122
FIRST = 240  # records of the first outbox: more than the fresh one holds
SECOND = 211  # records of the fresh one (the count)


def fill(path: Path, run: int, n: int) -> list[int]:
    """An outbox at path holding n records of this run; returns their idents."""
    box = Outbox(path, OutboxConfig())
    idents = [run * 100000 + i for i in range(n)]
    box.append_many([record(i) for i in idents])
    box.close()
    return idents


def send_until_drained(outbox: Path, port: Path, procs: list[subprocess.Popen[bytes]]) -> None:
    """Run the box's sender until every record of outbox is acknowledged, then cut its power."""
    sender = modem_cli("modem-send", str(outbox), str(port), "--bit-rate", "19200",
                       "--ack-timeout", "0.4", "--no-aggregate", "--no-ttl")  # fmt: skip
    procs.append(sender)
    queue = OutboxQueue(outbox, OutboxConfig())
    try:
        poll_for(lambda: queue.counts()[2] == 0, 40, what=f"{outbox.parent.name} to drain")
    finally:
        queue.close()
    sender.send_signal(signal.SIGKILL)  # the box goes down without a word
    sender.wait(timeout=10)


def idents_at(out: Path) -> list[int]:
    return [next(iter(json.loads(line).values()))["seq"] for line in out.read_text().splitlines()]


@pytest.mark.timeout(90)
@pytest.mark.parametrize("restart", ["new-run-directory", "deleted-outbox"])
def test_fresh_outbox_reaches_a_surface_that_stayed_up(
    tmp_path: Path, started_procs: list[subprocess.Popen[bytes]], restart: str
) -> None:
    """Regression for issue 16 item 1: the surface took the fresh outbox's ids (1, 2, ...)
    for retransmissions below its floor, acknowledged and dropped them, and the box marked
    them delivered: 211 of 211 records lost."""
    started_procs.append(modem_cli(
        "modem-sim", "--bit-rate", "19200", "--latency", "0.05", "--loss", "0.1",
        "--seed", str(SEED), "--link-a", str(tmp_path / "a"), "--link-b", str(tmp_path / "b")))
    poll_for(lambda: (tmp_path / "a").exists() and (tmp_path / "b").exists(), 20,
             what="the simulator's ends")  # fmt: skip
    out = tmp_path / "surface.jsonl"
    surface = modem_cli("surface", str(tmp_path / "b"), "-o", str(out))
    started_procs.append(surface)

    first_box = tmp_path / "run1" / "outbox.sqlite"
    first = fill(first_box, 1, FIRST)
    send_until_drained(first_box, tmp_path / "a", started_procs)
    assert sorted(idents_at(out)) == first

    if restart == "new-run-directory":
        second_box = tmp_path / "run2" / "outbox.sqlite"
    else:
        for f in first_box.parent.glob("outbox.sqlite*"):
            f.unlink()
        second_box = first_box
    second = fill(second_box, 2, SECOND)
    send_until_drained(second_box, tmp_path / "a", started_procs)

    surface.send_signal(signal.SIGTERM)
    _, err = surface.communicate(timeout=10)
    stats = json.loads(err.decode().strip().splitlines()[-1])
    got = idents_at(out)
    lost = sorted(set(second) - set(got))
    print(f"{restart}: surface {stats}; {len(lost)} of {SECOND} records of the fresh outbox lost")
    assert not lost, f"{len(lost)} of {SECOND} records of the fresh outbox never reached it"
    assert len(got) == len(set(got)), "a record was written twice"
    assert sorted(got) == first + second
    assert stats["new_sessions"] == 2
