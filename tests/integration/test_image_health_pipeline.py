"""Issue 33: a lens fouling on the synthetic world a few seconds into a run is flagged by
capture's image-health watch (its windows short), shown by `trapflow status`, kept in
ledger.json, and reaches the surface in a health record over the simulated acoustic link."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests.builders import small_source
from tests.conftest import REPO, Pipeline, only_pools, poll_for, write_config
from trapflow.cli.status_text import format_status

pytestmark = pytest.mark.slow  # starts a whole pipeline

ONSET_S = 4.0  # world time of the fouling's onset: pair 40 at 10 pairs/s


def _cli(*args: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen([sys.executable, "-m", "trapflow", *args], cwd=REPO,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _health(path: Path) -> list[dict]:
    if not path.exists():
        return []
    lines = [json.loads(x) for x in path.read_text().splitlines() if x.endswith("}")]
    return [r["health"] for r in lines if "health" in r]


@pytest.mark.timeout(90)
def test_fouling_is_flagged_and_reaches_the_surface(spawn, run_dir: Path,
                                                     started_procs) -> None:
    link = run_dir.parent
    started_procs.append(_cli("modem-sim", "--bit-rate", "2400", "--latency", "0.05",
                              "--seed", "3", "--link-a", str(link / "a"),
                              "--link-b", str(link / "b")))
    poll_for(lambda: (link / "a").exists() and (link / "b").exists(), 20, what="the ptys")
    surface_out = link / "surface.jsonl"
    started_procs.append(_cli("surface", str(link / "b"), "-o", str(surface_out)))
    cfg = write_config(link / "image.yaml", {
        "source": small_source(10.0, options={"fouling_onset_s": ONSET_S,
                                              "fouling_ramp_s": 2.0}),
        "pools": only_pools({"stereo": {"plugin": "histogram", "policy": "latest",
                                        "gate": "always"}}),
        "image_health": {"every_s": 0.3, "baseline_s": 2.0, "window_s": 1.0, "hold_s": 1.0},
        "modem": {"enabled": True, "port": str(link / "a"), "bit_rate": 2400.0,
                  "ack_timeout_s": 1.0, "reopen_interval_s": 0.5},
        "health": {"enabled": True, "interval_s": 600.0},  # only the first and the changes
    })
    p: Pipeline = spawn(["--config", str(cfg)], run_dir)
    p.wait_active()

    def fouled_at_surface() -> list[dict] | None:
        got = _health(surface_out)
        return got if any(h.get("image") == "fouled" for h in got) else None

    health = poll_for(fouled_at_surface, 40, interval=0.5, what="a fouled health record")
    fouled = next(h for h in health if h.get("image") == "fouled")
    sharp, contrast, _bright = fouled["image_ratio"]
    assert sharp < 0.5 and contrast > 0.8  # the fouling's own signature, not turbidity
    # Sent when the state changed (the baseline learnt: ok; then fouled), besides the first
    # record at the start: not per sample, and not waiting for the 10-minute interval.
    states = [h.get("image") for h in health]
    assert "ok" in states and len(health) <= 4, states
    st = p.status()
    assert st is not None and st["stats"]["image"]["state"] == "fouled"
    assert st["stats"]["image"]["changes"] == 1
    assert "image health: fouled; sharpness " in format_status(st)  # `trapflow status`
    code, _, err = p.stop(signal.SIGINT)
    assert code == 0, err
    ledger = json.loads((run_dir / "ledger.json").read_text())
    assert ledger["image_health"]["state"] == "fouled"
    assert (run_dir / "image_health.json").exists()  # the baseline a restart compares with
    log = (run_dir / "trapflow.log").read_text()
    assert log.count("image health: fouled (was ok)") == 1  # once, not per pair
