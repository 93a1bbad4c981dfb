"""`trapflow plan` as a subprocess: the documented month (configs/month.yaml) lasts at least
30 days, a finished run's ledger gives the costs, a bad input is one line and exit 2."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def _plan(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "trapflow", "plan", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=60)


def _days(stdout: str) -> float:
    m = re.search(r"^days on the battery: ([0-9.]+) on 1000 Wh", stdout, re.M)
    assert m, stdout
    return float(m.group(1))


def test_the_documented_month(tmp_path: Path) -> None:
    out = _plan("--config", "configs/month.yaml", "--date", "2026-12-01")
    assert out.returncode == 0, out.stderr
    assert _days(out.stdout) >= 30
    assert "windows a day: 24.0" in out.stdout
    assert "recording a day: 4.00 h" in out.stdout


def test_costs_from_a_finished_run(tmp_path: Path) -> None:
    """A run that kept two cores busy: the same month lasts fewer days; its modem's bytes
    give the airtime."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "ledger.json").write_text(json.dumps({
        "energy": {"wall_s": 600.0, "cpu_s_per_hour": {"mono": 3600.0, "vo": 3600.0}},
        "modem": {"bytes": 180}}))
    cfg = tmp_path / "c.yaml"
    cfg.write_text((REPO / "configs" / "month.yaml").read_text()
                   + "modem:\n  enabled: true\n  port: /dev/null\n")
    out = _plan("--config", str(cfg), "--from", str(run), "--date", "2026-12-01")
    assert out.returncode == 0, out.stderr
    assert "2.00 busy cores" in out.stdout
    assert 20 < _days(out.stdout) < 49
    # 1,080 bytes a recording hour, 4 h a day, 10 bits a byte at 300 bit/s
    assert "modem airtime a day: 144 s at 300 bit/s" in out.stdout


def test_bad_inputs_are_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("schedule:\n  every_min: 60\n  for_min: 90\n")
    for args in (["--config", str(bad)], ["--from", str(tmp_path / "no-run")]):
        out = _plan(*args)
        assert out.returncode == 2, out
        assert len(out.stderr.strip().splitlines()) == 1, out.stderr
        assert out.stderr.startswith("trapflow: error: ")
