"""The wake mechanism and `trapflow start`'s loop over recording windows, with fakes: a
temporary file stands for the RTC's wakealarm, a command records what it was asked, fake
clocks and a fake run stand for time and the pipeline. Nothing is powered off."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import pytest

from trapflow.config import schema as config
from trapflow.config.schedule import PowerConfig
from trapflow.errors import ConfigError
from trapflow.power import wake
from trapflow.power.schedule import Schedule, WindowClock
from trapflow.supervisor.run import RunResult
from trapflow.supervisor.windows import Clocks, run_scheduled

T0 = 1_796_083_200.0  # 2026-12-01 00:00 UTC
RECORD = "import sys; open(sys.argv[1], 'a').write(' '.join(sys.argv[2:]) + '\\n')"


def _recorder(tmp_path: Path, name: str, status: int = 0) -> tuple[str, Path]:
    """A command that appends its arguments to a file (and exits with `status`)."""
    script = tmp_path / f"{name}.py"
    script.write_text(RECORD + f"; sys.exit({status})\n")
    log = tmp_path / f"{name}.log"
    return f"{sys.executable} {script} {log}", log


def test_rtc_alarm_is_written(tmp_path: Path) -> None:
    alarm = tmp_path / "wakealarm"
    said = wake.set_wake(PowerConfig(rtc_path=str(alarm)), 1_796_086_710)
    assert alarm.read_text() == "1796086710\n"
    assert "1796086710" in said


def test_an_rtc_that_cannot_be_written_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(wake.WakeError, match="cannot set the wake alarm in .*missing"):
        wake.set_wake(PowerConfig(rtc_path=str(tmp_path / "missing" / "wakealarm")), 1)


def test_wake_and_poweroff_commands_are_run(tmp_path: Path) -> None:
    cmd, log = _recorder(tmp_path, "board")
    off, off_log = _recorder(tmp_path, "off")
    cfg = PowerConfig(wake="command", wake_command=f"{cmd} --wake-at {{epoch}}",
                      poweroff_command=f"{off} now")
    wake.set_wake(cfg, 1234)
    wake.power_off(cfg)
    assert log.read_text() == "--wake-at 1234\n"
    assert off_log.read_text() == "now\n"


def test_a_failing_command_is_one_line(tmp_path: Path) -> None:
    cmd, _ = _recorder(tmp_path, "board", status=3)
    with pytest.raises(wake.WakeError, match="exited with status 3"):
        wake.set_wake(PowerConfig(wake="command", wake_command=f"{cmd} {{epoch}}"), 1)
    with pytest.raises(wake.WakeError, match="could not run"):
        wake.power_off(PowerConfig(poweroff_command=str(tmp_path / "no-such-command")))


def test_the_window_clock_runs_on_the_monotonic_clock() -> None:
    s = Schedule(every_s=60.0, for_s=30.0)
    clock = WindowClock.start(s, mono=100.0, wall=T0 + 10)  # 20 s of the window left
    assert not clock.due(119.9, T0 + 29.9)
    assert not clock.due(110.0, T0 + 3600 + 40)  # a wall step forward does not end it
    assert not clock.due(120.0, T0 + 15.0)  # the wall clock stepped back: still inside,
    assert not clock.due(134.9, T0 + 29.9)  # for what the wall time says is left
    assert clock.due(135.0, T0 + 30.0)
    assert WindowClock.start(s, 0.0, T0 + 45).due(0.0, T0 + 45)  # outside: due at once


class FakeTime:
    """Wall and monotonic clocks that move only when slept or run through."""

    def __init__(self, wall: float) -> None:
        self.wall, self.mono = wall, 1000.0

    def advance(self, s: float) -> None:
        self.wall += s
        self.mono += s

    def clocks(self) -> Clocks:
        return Clocks(wall=lambda: self.wall, mono=lambda: self.mono, sleep=self.advance)


class FakeRun:
    """Runs that record when they began and last until their window's end (or stop)."""

    def __init__(self, t: FakeTime, ends: list[bool]) -> None:
        self.t, self.ends, self.began = t, ends, []

    def __call__(self, cfg: Any, run_dir: Any, duration: Any, *, out: Any, announce: Any,
                 window: WindowClock) -> RunResult:
        self.began.append(self.t.wall)
        ended = self.ends.pop(0)
        if ended:
            assert window.deadline is not None
            self.t.advance(window.deadline - self.t.mono)
            assert window.due(self.t.mono, self.t.wall)
        return RunResult(0, None, window_ended=ended)


def _cfg(tmp_path: Path, between: str, **power: Any) -> config.Config:
    return config.from_data({
        "schedule": {"every_min": 60, "for_min": 10, "between": between},
        "power": {"rtc_path": str(tmp_path / "wakealarm"), "boot_margin_s": 90, **power}})


def test_poweroff_at_the_end_of_a_window(tmp_path: Path) -> None:
    off, off_log = _recorder(tmp_path, "off")
    t = FakeTime(T0 + 5 * 3600 + 120)  # 05:02, inside 05:00-05:10
    runs, lines = FakeRun(t, [True]), []
    result = run_scheduled(_cfg(tmp_path, "poweroff", poweroff_command=off), clocks=t.clocks(),
                           run=runs, announce=lines.append)
    assert result.code == 0 and runs.began == [T0 + 5 * 3600 + 120]
    assert t.wall == T0 + 5 * 3600 + 600  # stopped at the window's end
    wake_at = int(T0 + 6 * 3600 - 90)  # the next window less the boot margin
    assert (tmp_path / "wakealarm").read_text() == f"{wake_at}\n"
    assert off_log.read_text() == "\n"  # the poweroff command ran once
    assert "the next window begins at 2026-12-01 06:00:00 UTC" in lines[-1]


def test_started_outside_a_window_idle_waits_then_records(tmp_path: Path) -> None:
    t = FakeTime(T0 + 5 * 3600 + 1800)  # 05:30
    runs, lines = FakeRun(t, [True, False]), []  # the second run stops on a signal
    run_scheduled(_cfg(tmp_path, "idle"), clocks=t.clocks(), run=runs, announce=lines.append)
    assert runs.began == [T0 + 6 * 3600, T0 + 7 * 3600]
    assert "the next begins at 2026-12-01 06:00:00 UTC" in lines[0]
    assert not (tmp_path / "wakealarm").exists()


def test_a_box_that_cannot_set_its_alarm_stays_up(tmp_path: Path) -> None:
    off, off_log = _recorder(tmp_path, "off")
    t = FakeTime(T0 + 5 * 3600 + 1800)
    runs = FakeRun(t, [False])
    cfg = _cfg(tmp_path, "poweroff", poweroff_command=off,
               rtc_path=str(tmp_path / "missing" / "wakealarm"))
    run_scheduled(cfg, clocks=t.clocks(), run=runs)
    assert runs.began == [T0 + 6 * 3600]  # waited up for the next window
    assert not off_log.exists()  # never powered off


def test_a_short_gap_is_waited_out(tmp_path: Path) -> None:
    off, off_log = _recorder(tmp_path, "off")
    t = FakeTime(T0 + 5 * 3600 + 3400)  # 05:56:40: the next window in 200 s
    runs = FakeRun(t, [False])
    run_scheduled(_cfg(tmp_path, "poweroff", poweroff_command=off), clocks=t.clocks(),
                  run=runs)
    assert runs.began == [T0 + 6 * 3600] and not off_log.exists()


def test_a_schedule_with_no_window_is_a_config_error(tmp_path: Path) -> None:
    cfg = config.from_data({"schedule": {"every_min": 60, "for_min": 10,
                                         "windows": ["06:20-06:40"]}})
    with pytest.raises(ConfigError, match="no recording window in the next 8 days"):
        run_scheduled(cfg, clocks=FakeTime(T0).clocks(), run=FakeRun(FakeTime(T0), []))


def test_no_schedule_is_one_plain_run() -> None:
    calls = []
    run_scheduled(config.Config(), run=lambda *a, **kw: calls.append(a) or RunResult(0, None))
    assert len(calls) == 1
