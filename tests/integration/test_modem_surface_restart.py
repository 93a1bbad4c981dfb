"""The ship end dies: kill -9 `trapflow surface` mid-stream, restart it, again and again.

The sender (in a thread here) retransmits what was not acknowledged, acks are lost on the
way; the output must still hold every record exactly once.
"""

from __future__ import annotations

import json
import random
import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest

from tests.conftest import modem_cli, modem_link, poll_for
from trapflow.config.modem import ModemConfig, OutboxConfig
from trapflow.modem.outbox import Outbox
from trapflow.modem.sender import ModemSender

SEED = 20250708
RECORDS = 120


def seqs(path: Path) -> list[int]:
    if not path.exists():
        return []
    lines = [line for line in path.read_text().splitlines() if line.endswith("}")]
    return [json.loads(line)["stereo_ir"]["seq"] for line in lines]


@pytest.mark.timeout(120)
def test_surface_killed_and_restarted_writes_each_record_once(
    tmp_path: Path, started_procs: list[subprocess.Popen[bytes]]
) -> None:
    print(f"surface-restart seed {SEED}")
    rng = random.Random(SEED)
    modem_link(tmp_path, started_procs, SEED, bit_rate="2400", loss="0.15")
    out = tmp_path / "surface.jsonl"
    box = Outbox(tmp_path / "outbox.sqlite", OutboxConfig())
    for i in range(RECORDS):
        box.append({"stereo_ir": {"timestamp": "2025-07-07 12:00:00.000", "seq": i,
                                  "label": "scallop", "confidence": 0.9}})  # fmt: skip
    cfg = ModemConfig(bit_rate=2400.0, ack_timeout_s=0.4, backoff_max_s=1.0,
                      reopen_interval_s=0.2)  # fmt: skip
    sender = ModemSender(tmp_path / "outbox.sqlite", str(tmp_path / "a"), cfg)
    halt = threading.Event()
    thread = threading.Thread(target=sender.run, args=(halt,))
    thread.start()
    kills = 0
    try:
        surface = modem_cli("surface", str(tmp_path / "b"), "-o", str(out))
        started_procs.append(surface)
        # Kill the surface at random moments while records are still arriving.
        while kills < 6 and len(seqs(out)) < RECORDS * 0.8:
            time.sleep(rng.uniform(0.3, 1.2))  # the random moment of the crash
            surface.send_signal(signal.SIGKILL)
            surface.wait(timeout=10)
            kills += 1
            surface = modem_cli("surface", str(tmp_path / "b"), "-o", str(out))
            started_procs.append(surface)
        poll_for(lambda: box.counts()[2] == 0, 60, what="the outbox to drain")
        stats = sender.stats()
    finally:
        halt.set()
        thread.join(timeout=10)
    surface.send_signal(signal.SIGTERM)
    _, err = surface.communicate(timeout=10)
    got = seqs(out)
    print(f"kills {kills}, sender {stats}\nlast surface {err.decode().strip().splitlines()[-1]}")
    assert kills >= 3, "the stream ended before the surface was killed mid-stream"
    assert stats["retransmits"] > 0
    assert len(got) == len(set(got)), "a record was written twice"
    assert sorted(got) == list(range(RECORDS))
    assert (tmp_path / "surface.jsonl.state").exists()
    box.close()
