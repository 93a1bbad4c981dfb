"""A fresh outbox against a surface that stayed up: the box is restarted with a new run
directory (or its outbox deleted) while `trapflow surface` and the link keep running.

Real processes: the link simulator, the surface receiver and the box's sender
(`modem-send`), over pseudo-terminals. The new outbox numbers its records from 1 again;
every one of them must reach the surface exactly once.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from tests.conftest import modem_cli, modem_link, send_until_drained, stop_surface, surface_idents
from tests.integration.modem_writer import record
from tests.reliability import figures
from trapflow.config.modem import OutboxConfig
from trapflow.modem.outbox import Outbox

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


@pytest.mark.timeout(90)
@pytest.mark.parametrize("restart", ["new-run-directory", "deleted-outbox"])
def test_fresh_outbox_reaches_a_surface_that_stayed_up(
    tmp_path: Path, started_procs: list[subprocess.Popen[bytes]], restart: str
) -> None:
    """Regression for issue 16 item 1: the surface took the fresh outbox's ids (1, 2, ...)
    for retransmissions below its floor, acknowledged and dropped them, and the box marked
    them delivered: 211 of 211 records lost."""
    modem_link(tmp_path, started_procs, SEED)
    out = tmp_path / "surface.jsonl"
    surface = modem_cli("surface", str(tmp_path / "b"), "-o", str(out))
    started_procs.append(surface)

    first_box = tmp_path / "run1" / "outbox.sqlite"
    first = fill(first_box, 1, FIRST)
    send_until_drained(first_box, tmp_path / "a", started_procs, "run1")
    assert sorted(surface_idents(out)) == first

    if restart == "new-run-directory":
        second_box = tmp_path / "run2" / "outbox.sqlite"
    else:
        for f in first_box.parent.glob("outbox.sqlite*"):
            f.unlink()
        second_box = first_box
    second = fill(second_box, 2, SECOND)
    send_until_drained(second_box, tmp_path / "a", started_procs, second_box.parent.name)

    stats = stop_surface(surface)
    got = surface_idents(out)
    lost = sorted(set(second) - set(got))
    print(f"{restart}: surface {stats}; {len(lost)} of {SECOND} records of the fresh outbox lost")
    figures(f"fresh_outbox_{restart}", records=FIRST + SECOND, lost=len(lost),
            duplicates=len(got) - len(set(got)))
    assert not lost, f"{len(lost)} of {SECOND} records of the fresh outbox never reached it"
    assert len(got) == len(set(got)), "a record was written twice"
    assert sorted(got) == first + second
    assert stats["new_sessions"] == 2
