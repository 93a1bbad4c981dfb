"""A run whose disk fills up (issue 33): on a small filesystem (a tmpfs with a size, mounted
for the test, unmounted after; skipped where mounting is not permitted) the normalizer keeps
going and counts the lines it could not write, the run stops cleanly on its duration, and
ledger.json is written whole from the space kept for it.

Regression: on a 20 MB run filesystem the normalizer crash-looped on "database or disk is
full", results after the fill were lost and counted nowhere, the run did not end, and at
the stop ledger.json was opened for writing and left empty (exit 1)."""

from __future__ import annotations

import json
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.builders import small_source
from tests.conftest import Pipeline, only_pools, write_config

pytestmark = pytest.mark.slow  # starts a whole pipeline

SIZE_MB = 20
LEFT_FREE = (1 << 20) + (48 << 10)  # the ledger's reserve (1 MiB) and 48 KiB for the run


@pytest.fixture
def small_disk() -> Iterator[Path]:
    """A 20 MB tmpfs, unmounted (and its folder removed) after the test."""
    where = Path(tempfile.mkdtemp(prefix="tf-full-"))
    got = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={SIZE_MB}m", "tmpfs",
                          str(where)], capture_output=True, text=True, check=False)
    if got.returncode != 0:
        where.rmdir()
        pytest.skip(f"cannot mount a small filesystem here: {got.stderr.strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)
        where.rmdir()


@pytest.mark.timeout(240)
def test_a_full_disk_is_counted_and_the_ledger_survives(spawn, small_disk: Path) -> None:
    run_dir = small_disk / "run"
    cfg = write_config(small_disk.parent / f"{small_disk.name}.yaml", {
        "source": small_source(10.0, seed=5),
        "pools": only_pools({"vo": {"count": 1}}),
        "log_file": {"max_bytes": 1 << 20, "backups": 1}})
    filler = small_disk / "filler"
    with open(filler, "wb") as fh:  # leave the run LEFT_FREE bytes
        fh.truncate(0)
        fh.write(bytes(shutil.disk_usage(small_disk).free - LEFT_FREE))
    try:
        p: Pipeline = spawn(["--config", str(cfg), "--duration", "25"], run_dir)
        code, out, err = p.wait(200)
    finally:
        cfg.unlink()
    assert code == 0, (out[-2000:], err[-2000:])
    ledger = json.loads((run_dir / "ledger.json").read_text())
    lost = ledger["not_written_disk_full"]
    assert lost.get("results.jsonl", 0) > 0, ledger
    assert "not written, the disk full" in out
    lines = (run_dir / "results.jsonl").read_bytes()
    assert lines.endswith(b"\n") and all(json.loads(x) for x in lines.splitlines())
    restarts = ledger["pools"]["vo"]["restarts"]
    assert restarts == 0 and "normalizer" not in json.dumps(ledger.get("supervision", {})), (
        ledger.get("supervision"))
    assert json.loads((run_dir / "run.json").read_text())["duration_s"] > 20
