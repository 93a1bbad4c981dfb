"""The surface's first run keeps its state: `trapflow surface PORT -o NEWFILE` writes
NEWFILE.state, so a restarted surface writes a retransmission only once.

Regression for issue 26 item 8: without --state, the state file was kept only when the
output already existed, so the first run saved nothing (`state_saves: 0` in both power-cut
runs of the issue) and a surface restarted after it wrote every retransmission again.
Real processes: the link simulator, the surface and the box's sender (`modem-send`). The
box's power cut before its acknowledgements were saved is a copy of its outbox taken before
they came: sent again whole, in the same session, to the restarted surface.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.conftest import modem_cli, modem_link, send_until_drained, stop_surface, surface_idents
from tests.reliability.test_modem_fresh_outbox import fill

SEED = 20261125
RECORDS = 40


@pytest.mark.timeout(90)
def test_first_run_keeps_state_and_a_restart_writes_retransmissions_once(
        tmp_path: Path, started_procs: list[subprocess.Popen[bytes]]) -> None:
    modem_link(tmp_path, started_procs, SEED)
    box = tmp_path / "box" / "outbox.sqlite"
    sent = fill(box, 1, RECORDS)
    unacked = tmp_path / "unacked"  # the box's outbox as a power cut would leave it
    unacked.mkdir()
    for f in box.parent.glob("outbox.sqlite*"):
        shutil.copy2(f, unacked / f.name)
    out = tmp_path / "new" / "surface.jsonl"
    out.parent.mkdir()
    assert not out.exists()  # the first run: no output yet

    surface = modem_cli("surface", str(tmp_path / "b"), "-o", str(out))
    started_procs.append(surface)
    send_until_drained(box, tmp_path / "a", started_procs, "the first outbox")
    first = stop_surface(surface)
    state = out.with_name(out.name + ".state")
    assert first["state_saves"] >= 1, first
    assert state.exists(), "the first run kept no state"
    assert json.loads(state.read_text())["sessions"], state.read_text()
    assert sorted(surface_idents(out)) == sent

    restarted = modem_cli("surface", str(tmp_path / "b"), "-o", str(out))
    started_procs.append(restarted)
    send_until_drained(unacked / "outbox.sqlite", tmp_path / "a", started_procs,
                       "the retransmissions")
    second = stop_surface(restarted)
    got = surface_idents(out)
    print(f"first run {first}\nrestarted {second}")
    assert len(got) == len(set(got)), f"{len(got) - len(set(got))} retransmissions written again"
    assert sorted(got) == sent
