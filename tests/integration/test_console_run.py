"""The console of a real `trapflow start` tells the truth (issue 15): `--duration` counts
from the first captured pair, a planned stop leaves nothing "lost", the status line fits
80 columns, a normal end prints no warning, and the exit names what the run left."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from tests.builders import NOISE_H as H
from tests.builders import NOISE_W as W
from tests.builders import write_recording
from tests.conftest import Pipeline, write_config
from trapflow.recording.recorder import TOPIC_LEFT, TOPIC_RIGHT
from trapflow.supervisor.ledger import STATUS_WIDTH, UNFINISHED

pytestmark = pytest.mark.slow  # starts whole pipelines

STATUS_LINE = re.compile(r"^ *\d+\.\ds \| ")


def _config(path: Path, **extra: object) -> Path:
    return write_config(path, {"pools": {"every": {"plugin": "digest", "policy": "ordered:64"}},
                               **extra})


def _accounted(ledger: dict, pool: str) -> int:
    p = ledger["pools"][pool]
    return (p["processed"] + p["dropped_by_policy"] + p["timed_out"] + p["failed"] + p["lost"]
            + p.get(UNFINISHED, 0))


def _delivered(run_dir: Path) -> int:
    lines = (run_dir / "results.jsonl").read_text().splitlines()
    return len({json.loads(x)["digest"]["seq"] for x in lines if x.strip()})


@pytest.mark.timeout(120)
def test_duration_counts_from_the_first_pair_and_the_stop_loses_nothing(
        spawn, run_dir: Path) -> None:
    """Regression (issue 15): `--duration 20` at 15 Hz gave 205 pairs (boot ate the rest),
    and the stop reported the pairs still on their way as lost."""
    rate, duration = 10, 3
    cfg = _config(run_dir.parent / "c.yaml")
    p: Pipeline = spawn(["--config", str(cfg), "--workers", "every=1", "--size", f"{W}x{H}",
                         "--rate", str(rate), "--duration", str(duration)], run_dir)
    code, out, err = p.wait(90)
    assert code == 0, err
    ledger = json.loads((run_dir / "ledger.json").read_text())
    # The duration's worth of pairs; a little over for the stop (capture is told first).
    assert rate * duration * 0.85 <= ledger["produced"] <= rate * duration * 1.25, ledger
    every = ledger["pools"]["every"]
    assert every["lost"] == 0 and UNFINISHED in every, every
    assert _accounted(ledger, "every") == ledger["produced"], ledger
    status = [line for line in out.splitlines() if STATUS_LINE.match(line)]
    assert status and all(len(line) <= STATUS_WIDTH for line in status), status
    assert f"lost 0, unfinished at stop {every[UNFINISHED]}," in out
    assert f"results: {run_dir / 'results.jsonl'} ({_delivered(run_dir)} results)" in out, out
    assert "source exhausted" not in err and "link port inactive" not in err, err


@pytest.mark.timeout(120)
def test_a_finite_replay_ends_without_a_warning_and_names_its_topics(
        spawn, run_dir: Path) -> None:
    """Regression (issue 15): every finite run ended with `WARNING capture: finalized (source
    exhausted)`, and the exit did not say which topics a recording was replayed from."""
    rec = run_dir.parent / "rec.mcap"
    write_recording(rec, 12)
    cfg = _config(run_dir.parent / "c.yaml", events={"enabled": True})
    p: Pipeline = spawn(["--config", str(cfg), "--workers", "every=1", "--size", f"{W}x{H}",
                         "--source", f"replay:{rec}"], run_dir)
    code, out, err = p.wait(90)
    assert code == 0, err
    assert [line for line in err.splitlines() if "WARNING" in line] == [], err
    assert f"replayed: {TOPIC_LEFT} and {TOPIC_RIGHT} in {rec}" in out.splitlines(), out
    events = run_dir / "events"
    written = sum(1 for d in events.iterdir() if d.is_dir()) if events.is_dir() else 0
    assert f"events: {written} written in {events}" in out.splitlines(), out
    ledger = json.loads((run_dir / "ledger.json").read_text())
    assert ledger["produced"] == 12 and ledger["pools"]["every"]["processed"] == 12, ledger
    assert f"results: {run_dir / 'results.jsonl'} (12 results)" in out, out
