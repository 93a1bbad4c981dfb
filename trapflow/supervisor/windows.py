"""`trapflow start` under a schedule: one run per recording window, and between two windows
either wait up (pipeline stopped) or set the wake alarm and power off.

The decisions are trapflow.power.schedule's (inside a window, its end, the next start, idle
or poweroff); the alarm and the poweroff are trapflow.power.wake's. This shell reads the wall
clock only to decide windows: each wait and each window's end is a monotonic deadline, and
at its end the wall time decides again. Without a schedule it is one plain run.
"""

from __future__ import annotations

import datetime as dt
import logging
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from trapflow.config.schema import Config
from trapflow.errors import ConfigError
from trapflow.power import wake
from trapflow.power.schedule import (
    HORIZON_S,
    Idle,
    PowerOff,
    Schedule,
    WindowClock,
    between,
    from_config,
    verdict,
)
from trapflow.runtime import sdnotify
from trapflow.supervisor import run as run_module
from trapflow.supervisor.run import RunResult

log = logging.getLogger(__name__)

WAIT_STEP_S = 1.0  # a wait wakes this often: signals, systemd's watchdog


def utc_text(epoch: float) -> str:
    """An epoch second as `2026-12-01 06:00:00 UTC`."""
    return dt.datetime.fromtimestamp(epoch, dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")


@dataclass
class Clocks:
    """The clocks and the sleep a scheduled start uses (tests pass their own)."""

    wall: Callable[[], float] = time.time
    mono: Callable[[], float] = time.monotonic
    sleep: Callable[[float], None] = time.sleep


@dataclass
class _Signals:
    """SIGINT and SIGTERM end a wait between windows (a run installs its own)."""

    stop: bool = False
    old: dict[int, Any] = field(default_factory=dict)

    def __enter__(self) -> _Signals:
        for signo in (signal.SIGINT, signal.SIGTERM):
            self.old[signo] = signal.signal(signo, self._on)
        return self

    def _on(self, signo: int, _frame: Any) -> None:
        log.info("received %s while waiting for a window, stopping", signal.Signals(signo).name)
        self.stop = True

    def __exit__(self, *exc: object) -> None:
        for signo, handler in self.old.items():
            signal.signal(signo, handler)


def run_scheduled(cfg: Config, run_dir: Path | None = None, duration: float | None = None,
                  out: IO[str] | None = None, announce: Callable[[str], None] | None = None,
                  *, clocks: Clocks | None = None,
                  run: Callable[..., RunResult] | None = None) -> RunResult:
    """Record in every window of cfg.schedule until a signal, --duration, a failed run, or
    the board powering off; without a schedule, one run as before."""
    run = run or run_module.run  # looked up now: a test may stand in for it
    schedule = from_config(cfg.schedule)
    if schedule is None:
        return run(cfg, run_dir, duration, out=out, announce=announce)
    clocks = clocks or Clocks()
    say = announce or (lambda line: None)
    notifier = sdnotify.Notifier()
    last = RunResult(0, None)
    while True:
        now = clocks.wall()
        v = verdict(schedule, now)
        if v.inside:
            say(f"recording window until {utc_text(v.ends_at)}" if v.ends_at is not None
                else "recording window with no end in sight")
            last = run(cfg, run_dir, duration, out=out, announce=announce,
                       window=WindowClock.start(schedule, clocks.mono(), now))
            if last.code != 0 or not last.window_ended:
                return last  # a failure, a signal, --duration or the source's end
            continue
        action = between(v, now, cfg.schedule.between, cfg.power.boot_margin_s,
                         cfg.power.min_off_s)
        if isinstance(action, PowerOff):
            if _power_off(cfg, action, say):
                return last
            action = Idle(action.next_start)
        if action.until is None:
            raise ConfigError(f"the schedule has no recording window in the next "
                              f"{HORIZON_S / 86400:g} days")
        say(f"outside the recording windows; the next begins at {utc_text(action.until)}, "
            "waiting (pipeline stopped)")
        if not _wait(schedule, action.until, clocks, notifier):
            return last


def _power_off(cfg: Config, action: PowerOff, say: Callable[[str], None]) -> bool:
    """Set the alarm, then power off; False (stay up) if either fails: a box that cannot
    wake must not go down."""
    try:
        done = wake.set_wake(cfg.power, action.wake_at)
        say(f"the next window begins at {utc_text(action.next_start)}; {done} "
            f"(wake at {utc_text(action.wake_at)}); powering off")
        wake.power_off(cfg.power)
    except wake.WakeError as exc:
        log.error("%s; staying up until the next window instead of powering off", exc)
        say(f"{exc}; staying up until the next window instead of powering off")
        return False
    return True


def _wait(schedule: Schedule, until: float, clocks: Clocks,
          notifier: sdnotify.Notifier) -> bool:
    """Wait for the window at `until` (wall): a monotonic deadline, then the wall clock
    decides again. False when a signal ended the wait."""
    with _Signals() as signals:
        notifier.ready(f"waiting for the recording window at {utc_text(until)}")
        deadline = clocks.mono() + max(0.0, until - clocks.wall())
        while not signals.stop:
            left = deadline - clocks.mono()
            if left <= 0:
                v = verdict(schedule, clocks.wall())
                if v.inside or v.next_start is None:
                    return True
                deadline = clocks.mono() + max(0.0, v.next_start - clocks.wall())
                continue
            if notifier.enabled and notifier.watchdog_s:
                notifier.watchdog()
            clocks.sleep(min(left, WAIT_STEP_S))
        return False
