"""Power cuts on the modem leg, with outboxes swapped: kill -9 the box's process group
(writer + sender) at random moments, bring it back on the same outbox or on another one
(a fresh SD card, later swapped back), while the link simulator and `trapflow surface`
stay up. Afterwards every outbox is drained in turn.

Invariants: every record whose append() returned is in its outbox, intact, and
acknowledged; the surface holds every record of every outbox exactly once.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import (
    MODEM_SEND_ARGS,
    modem_cli,
    modem_link,
    poll_for,
    send_until_drained,
    stop_surface,
    surface_idents,
)
from tests.integration.modem_writer import record
from tests.reliability import figures, scaled
from trapflow.config.modem import OutboxConfig
from trapflow.modem.outbox import OutboxQueue

SEED = 20261123
WRITER = Path(__file__).parent.parent / "integration" / "modem_writer.py"
# The outbox each power-up runs on: Y and Z are fresh when first used (the surface has
# heard X by then), X and Y come back after another outbox ran.
SCHEDULE = ["X", "X", "Y", "X", "Z", "Y", "X", "Z"]
# scripts/chaos.sh asks for more power cuts: the schedule goes on, fresh outboxes included
# (a new outbox name every round).
CUTS = int(scaled("TRAPFLOW_CHAOS_POWERCUTS", len(SCHEDULE)))
SCHEDULE = [f"{n}{i // len(SCHEDULE)}" if i >= len(SCHEDULE) else n
            for i, n in ((i, SCHEDULE[i % len(SCHEDULE)]) for i in range(CUTS))]


def start_box(outbox_dir: Path, port: Path, run: int) -> subprocess.Popen[bytes]:
    """The box: one session (process group) holding the writer and the sender."""
    outbox = outbox_dir / "outbox.sqlite"
    script = (
        "import subprocess, sys\n"
        f"w = subprocess.Popen([sys.executable, {str(WRITER)!r}, {str(outbox)!r}, "
        f"{str(outbox_dir / 'acks.log')!r}, '{run}'])\n"
        "s = subprocess.Popen([sys.executable, '-m', 'trapflow.cli.modem', 'modem-send', "
        f"{str(outbox)!r}, {str(port)!r}, *{MODEM_SEND_ARGS!r}], stderr=subprocess.DEVNULL)\n"
        "w.wait(); s.wait()\n"
    )
    return subprocess.Popen([sys.executable, "-c", script], start_new_session=True)


def cut_power(box: subprocess.Popen[bytes]) -> None:
    os.killpg(box.pid, signal.SIGKILL)
    box.wait(timeout=10)


def acknowledged(outbox_dir: Path) -> list[tuple[int, int]]:
    """(seq, ident) of every append that returned, from the writer's log."""
    log = outbox_dir / "acks.log"
    if not log.exists():
        return []
    rows = [line.split() for line in log.read_text().splitlines()]
    return [(int(a), int(b)) for a, b, *_ in (r for r in rows if len(r) == 2)]


@pytest.mark.timeout(int(60 + 10 * CUTS))
def test_power_cuts_with_fresh_outboxes_lose_nothing(
    tmp_path: Path, started_procs: list[subprocess.Popen[bytes]]
) -> None:
    """Regression for issue 16 item 1 under power cuts: a fresh outbox's records were taken
    for retransmissions of the previous outbox, acknowledged and dropped by the surface."""
    print(f"power-cut sessions seed {SEED}")
    rng = random.Random(SEED)
    modem_link(tmp_path, started_procs, SEED)
    out = tmp_path / "surface.jsonl"
    surface = modem_cli("surface", str(tmp_path / "b"), "-o", str(out))
    started_procs.append(surface)
    dirs = {name: tmp_path / f"run-{name}" for name in sorted(set(SCHEDULE))}
    for run, name in enumerate(SCHEDULE, start=1):
        before = len(acknowledged(dirs[name]))
        box = start_box(dirs[name], tmp_path / "a", run)
        try:
            # The box is up once its writer appends; it runs on for a random while.
            poll_for(lambda: len(acknowledged(dirs[name])) > before, 30,  # noqa: B023
                     what=f"the writer of power-up {run} to append")  # fmt: skip
            time.sleep(rng.uniform(0.3, 1.5))  # the random moment of the power cut
        finally:
            cut_power(box)

    # Power back for good: each outbox in turn is drained by its sender alone.
    for name, outbox_dir in dirs.items():
        send_until_drained(outbox_dir / "outbox.sqlite", tmp_path / "a", started_procs,
                           f"outbox {name}")

    stats = stop_surface(surface)
    at_surface = surface_idents(out)
    print(f"surface: {stats}")

    expected: list[int] = []
    for name, outbox_dir in dirs.items():
        queue = OutboxQueue(outbox_dir / "outbox.sqlite", OutboxConfig())
        try:
            assert queue.integrity_check() == [], f"outbox {name} damaged"
            stored = {s.seq: s for s in queue.read()}
            acks = acknowledged(outbox_dir)
            assert acks, f"outbox {name} never got a record"
            for seq, ident in acks:
                assert seq in stored, f"outbox {name}: record {seq} (id {ident}) acknowledged "
                "as stored but missing"
                assert stored[seq].intact and stored[seq].record() == record(ident)
            assert queue.states() == {"acked": len(stored)}, f"outbox {name}"
            expected += [next(iter(s.record().values()))["seq"] for s in stored.values()]
        finally:
            queue.close()
        print(f"outbox {name}: {len(stored)} records, {len(acks)} appends acknowledged")
    missing = sorted(set(expected) - set(at_surface))
    figures("modem_power_cuts", cuts=len(SCHEDULE), outboxes=len(dirs),
            acknowledged=len(expected), at_surface=len(at_surface), lost=len(missing),
            duplicates=len(at_surface) - len(set(at_surface)))
    assert not missing, f"{len(missing)} acknowledged records never reached the surface"
    assert len(at_surface) == len(set(at_surface)), "a record was written twice"
    assert sorted(at_surface) == sorted(expected)
    assert stats["new_sessions"] == len(dirs)
