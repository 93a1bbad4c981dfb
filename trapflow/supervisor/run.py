"""Run a pipeline from start to end: the run directory (made, then removed again if the start
fails before capture), the supervisor, and how it ended."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from trapflow.config.schema import Config
from trapflow.power.schedule import WindowClock
from trapflow.supervisor import ledger as run_ledger
from trapflow.supervisor.setup import default_run_dir, discard_run_dir
from trapflow.supervisor.shell import Supervisor
from trapflow.wire import messages


@dataclass
class RunResult:
    """How a run ended: its exit status, the run's totals, and the one-line failure if any."""

    code: int
    stats: messages.Stats | None
    failure: str | None = None
    capture_failures: dict[str, int] = field(default_factory=dict)  # pairs skipped, by kind
    window_ended: bool = False  # stopped at the end of the schedule's recording window


def run(cfg: Config, run_dir: Path | None = None, duration: float | None = None,
        out: IO[str] | None = None, announce: Callable[[str], None] | None = None,
        window: WindowClock | None = None) -> RunResult:
    """Run a pipeline until duration, a signal, or the end of a finite source.

    Returns the exit status, the last stats the broker published (the run's totals) and,
    when the status is 1, the line that says why.
    """
    latest = run_dir is None
    if run_dir is None:
        run_dir = default_run_dir()
    created = not run_dir.exists()
    run_dir.mkdir(parents=True, exist_ok=True)
    if announce:
        announce(f"run directory: {run_dir}")
    sup = Supervisor(cfg, run_dir, duration, out, latest=latest, window=window)
    try:
        code = sup.run()
    finally:
        if created and not sup.started:  # it failed before capture: no run to leave behind
            discard_run_dir(run_dir)
    return RunResult(code, sup.stats, sup.failure,
                     run_ledger.capture_failures(sup.capture_counts()), sup.window_ended)


def start(cfg: Config, run_dir: Path | None = None, duration: float | None = None,
          out: IO[str] | None = None, announce: Callable[[str], None] | None = None) -> int:
    """run(), returning only the exit status."""
    return run(cfg, run_dir, duration, out, announce).code
