"""Power cut: kill -9 the box's process tree (writer + sender) at random moments, restart, check.

The simulator and the surface receiver stay up (they are on the ship). Invariants: every
record whose append() returned is in the outbox, intact; the outbox passes its integrity
check; the surface writes every record exactly once, in order per class.
"""

from __future__ import annotations

import collections
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import poll_for
from trapflow.config.modem import OutboxConfig
from trapflow.modem.outbox import OutboxQueue

sys.path.insert(0, str(Path(__file__).parent))
from modem_writer import record

SEED = 20250707
CYCLES = 15
HERE = Path(__file__).parent



def cli(*args: str, **kw: object) -> subprocess.Popen[bytes]:
    return subprocess.Popen([sys.executable, "-m", "trapflow.cli.modem", *args], **kw)  # type: ignore[call-overload]


def start_box(tmp: Path, run: int) -> subprocess.Popen[bytes]:
    """The box: one session (process group) holding the writer and the sender."""
    script = (
        "import subprocess, sys\n"
        f"w = subprocess.Popen([sys.executable, {str(HERE / 'modem_writer.py')!r}, "
        f"{str(tmp / 'outbox.sqlite')!r}, {str(tmp / 'acks.log')!r}, '{run}'])\n"
        "s = subprocess.Popen([sys.executable, '-m', 'trapflow.cli.modem', 'modem-send', "
        f"{str(tmp / 'outbox.sqlite')!r}, {str(tmp / 'a')!r}, '--bit-rate', '19200', "
        "'--ack-timeout', '0.4', '--no-aggregate', '--no-ttl'], stderr=subprocess.DEVNULL)\n"
        "w.wait(); s.wait()\n"
    )
    return subprocess.Popen([sys.executable, "-c", script], start_new_session=True)


def kill_tree(proc: subprocess.Popen[bytes]) -> None:
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=10)


@pytest.mark.timeout(150)
def test_power_cut_loses_nothing_and_sends_nothing_twice(tmp_path: Path) -> None:
    print(f"power-cut seed {SEED}")
    rng = random.Random(SEED)
    sim = cli(
        "modem-sim",
        "--bit-rate",
        "19200",
        "--latency",
        "0.05",
        "--loss",
        "0.1",
        "--seed",
        str(SEED),
        "--link-a",
        str(tmp_path / "a"),
        "--link-b",
        str(tmp_path / "b"),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    procs: list[subprocess.Popen[bytes]] = [sim]
    try:
        poll_for(lambda: (tmp_path / "b").exists(), 20, what="the simulator's ends")
        out = tmp_path / "surface.jsonl"
        surface = cli("surface", str(tmp_path / "b"), "-o", str(out), stderr=subprocess.PIPE)
        procs.append(surface)
        for run in range(1, CYCLES + 1):
            box = start_box(tmp_path, run)
            procs.append(box)
            time.sleep(rng.uniform(0.3, 2.0))  # the random moment of the power cut
            kill_tree(box)
            procs.remove(box)
        # Power back for good: the sender alone drains the outbox.
        queue = OutboxQueue(tmp_path / "outbox.sqlite", OutboxConfig())
        sender = cli(
            "modem-send",
            str(tmp_path / "outbox.sqlite"),
            str(tmp_path / "a"),
            "--bit-rate",
            "19200",
            "--ack-timeout",
            "0.4",
            "--no-aggregate",
            "--no-ttl",
            stderr=subprocess.DEVNULL,
        )
        procs.append(sender)
        poll_for(lambda: queue.counts()[2] == 0, 60, what="the outbox to drain")
        acks = [
            tuple(map(int, line.split()))
            for line in (tmp_path / "acks.log").read_text().splitlines()
            if len(line.split()) == 2
        ]

        assert queue.integrity_check() == []
        stored = {s.seq: s for s in queue.read()}
        assert len(acks) > CYCLES * 5
        for seq, ident in acks:
            assert seq in stored, f"record {seq} (id {ident}) acknowledged as stored but missing"
            assert stored[seq].intact
            assert stored[seq].record() == record(ident)
        assert queue.states() == {"acked": len(stored)}

        surface.send_signal(signal.SIGTERM)
        _, err = surface.communicate(timeout=10)
        procs.remove(surface)
        lines = [json.loads(line) for line in out.read_text().splitlines()]
        idents = [next(iter(r.values()))["seq"] for r in lines]
        assert len(idents) == len(set(idents)), "a record reached the surface twice as new"
        assert sorted(idents) == sorted(
            json.loads(s.body)[next(iter(json.loads(s.body)))]["seq"] for s in stored.values()
        )
        per_class: dict[str, list[int]] = collections.defaultdict(list)
        for rec, ident in zip(lines, idents, strict=True):
            per_class[next(iter(rec))].append(ident)
        for name, ids in per_class.items():
            assert ids == sorted(ids), f"{name} out of order at the surface"
        stats = json.loads(err.decode().strip().splitlines()[-1])
        print(f"surface: {stats}")
        queue.close()
    finally:
        for proc in procs:
            if proc.poll() is None:
                if proc.args[:2] == [sys.executable, "-c"]:
                    kill_tree(proc)
                else:
                    proc.kill()
                    proc.wait(timeout=10)
