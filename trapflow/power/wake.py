"""The wake mechanism, a thin shell: set the board's wake alarm for the next recording
window (the RTC's wakealarm file or a power board's command), then power off. What to do
and when is trapflow.power.schedule's; this module only writes and runs.

A box that cannot set its alarm must not power off (it would never wake): every failure
here is a WakeError, and the caller stays up instead.
"""

from __future__ import annotations

import shlex
import subprocess
from pathlib import Path

from trapflow.config.schedule import PowerConfig

COMMAND_TIMEOUT_S = 30.0


class WakeError(Exception):
    """The alarm could not be set, or the poweroff command failed: one line, why."""


def _run(argv: list[str], what: str) -> None:
    try:
        done = subprocess.run(argv, capture_output=True, text=True, timeout=COMMAND_TIMEOUT_S,
                              check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise WakeError(f"{what} {shlex.join(argv)!r} could not run: {exc}") from None
    if done.returncode != 0:
        said = (done.stderr or done.stdout).strip().splitlines()
        raise WakeError(f"{what} {shlex.join(argv)!r} exited with status {done.returncode}"
                        + (f": {said[-1]}" if said else ""))


def set_wake(cfg: PowerConfig, epoch: int) -> str:
    """Set the wake alarm at `epoch` (UTC seconds); returns what was done, in words."""
    if cfg.wake == "rtc":
        path = Path(cfg.rtc_path)
        try:  # the kernel refuses a new alarm while one is set: 0 clears it first
            path.write_text("0\n")
            path.write_text(f"{epoch}\n")
        except OSError as exc:
            raise WakeError(f"cannot set the wake alarm in {path}: {exc.strerror or exc}"
                            ) from None
        return f"wake alarm {epoch} written to {path}"
    if cfg.wake == "command":
        argv = shlex.split(cfg.wake_command.format(epoch=epoch))
        _run(argv, "wake command")
        return f"wake command {shlex.join(argv)!r} ran"
    raise WakeError("power.wake is none: no alarm can be set")


def power_off(cfg: PowerConfig) -> None:
    """Run the poweroff command (it returns while the system goes down)."""
    _run(shlex.split(cfg.poweroff_command), "poweroff command")
