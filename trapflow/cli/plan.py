"""`trapflow plan`: what a config's schedule costs a battery before the box goes in the
water: windows, recording hours, Wh a day and days on the battery, from the board model of
ledger.json's energy line (trapflow.power.plan) and the recording costs of a finished run
(`--from RUN_DIR`) or the model's defaults."""

from __future__ import annotations

import datetime as dt
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click

from trapflow.cli.exit import CommandFailed
from trapflow.config import schema as configmod
from trapflow.config.schema import Config
from trapflow.errors import EXIT_USAGE, TrapflowError
from trapflow.power.energy import BOARDS, RECORDING_CPU_S_PER_HOUR
from trapflow.power.plan import Plan, airtime_s, plan, split_day
from trapflow.power.schedule import from_config


@dataclass(frozen=True)
class Costs:
    """What an hour of recording costs: CPU per role, modem bytes, and where they come from."""

    cpu_s_per_hour: dict[str, float]
    modem_bytes_per_hour: float | None
    origin: str


def costs_from_run(run_dir: Path) -> Costs:
    """A finished run's costs: ledger.json's `energy` (CPU seconds per role an hour) and its
    modem's bytes over the run's wall time."""
    path = run_dir / "ledger.json"
    try:
        ledger = json.loads(path.read_text(encoding="utf-8"))
        energy = ledger["energy"]
        per_hour = {str(k): float(v) for k, v in energy["cpu_s_per_hour"].items()}
        wall_s = float(energy["wall_s"])
    except OSError as exc:
        raise CommandFailed(f"--from {run_dir}: cannot read {path.name}: {exc.strerror}; "
                            "expected a finished run's directory", EXIT_USAGE) from None
    except (ValueError, KeyError, TypeError, AttributeError):
        raise CommandFailed(f"--from {run_dir}: {path.name} has no energy section with "
                            "cpu_s_per_hour and wall_s", EXIT_USAGE) from None
    sent = ledger.get("modem", {}).get("bytes") if isinstance(ledger.get("modem"), dict) else None
    bytes_per_hour = float(sent) * 3600.0 / wall_s if sent is not None and wall_s > 0 else None
    return Costs(per_hour, bytes_per_hour, f"the run in {run_dir} ({wall_s:g} s)")


def _hours(seconds: float) -> str:
    return f"{seconds / 3600:.2f} h"


def _schedule_text(cfg: Config) -> str:
    s, p = cfg.schedule, cfg.power
    if not s.enabled:
        return "none (always recording)"
    rules = []
    if s.every_min > 0:
        rules.append(f"every {s.every_min:g} min for {s.for_min:g} min"
                     + (f" from :{s.offset_min:g}" if s.offset_min else ""))
    if s.windows:
        rules.append("UTC " + ", ".join(s.windows))
    if s.sun_margin_min > 0:
        rules.append(f"{s.sun_margin_min:g} min off either side of sunrise and sunset")
    how = (f"poweroff (wake {p.wake}, {p.boot_margin_s:g} s boot margin)"
           if s.between == "poweroff" else "idle")
    return f"{'; '.join(rules)}; between windows: {how}"


def plan_lines(cfg: Config, costs: Costs, day: dt.date, days: int) -> list[str]:
    """The plan, as the lines the command prints."""
    s, e = cfg.schedule, cfg.energy
    split = split_day(from_config(s), day, days, s.between, cfg.power.boot_margin_s,
                      cfg.power.min_off_s)
    p: Plan = plan(BOARDS[e.board], split, costs.cpu_s_per_hour, cameras=e.cameras,
                   battery_wh=e.battery_wh, usable=e.usable)
    busy = sum(costs.cpu_s_per_hour.values()) / 3600.0
    lines = [
        f"plan ({e.board} model, {e.cameras} cameras; {days} UTC days from {day})",
        f"schedule: {_schedule_text(cfg)}",
        f"recording costs: {busy:.2f} busy cores, from {costs.origin}",
        f"windows a day: {split.windows:.1f}",
        f"recording a day: {_hours(split.recording_s)} at {p.recording_w:.2f} W",
    ]
    if split.booting_s or split.off_s:
        lines.append(f"booting a day: {_hours(split.booting_s)} at {p.booting_w:.2f} W; "
                     f"off: {_hours(split.off_s)} at {p.off_w:.2f} W")
    if split.idle_s:
        lines.append(f"idle a day: {_hours(split.idle_s)} at {p.idle_w:.2f} W")
    lines.append(f"energy: {p.wh_per_day:.1f} Wh a day")
    if p.days is not None:
        lines.append(f"days on the battery: {p.days:.1f} on {e.battery_wh:g} Wh "
                     f"({100 * e.usable:g} % usable)")
    else:
        lines.append("days on the battery: set energy.battery_wh to know")
    if cfg.modem.enabled:
        up = f"the modem sends only while recording: at most {_hours(split.recording_s)} a day"
        if costs.modem_bytes_per_hour is not None:
            air = airtime_s(costs.modem_bytes_per_hour, split, cfg.modem.bit_rate)
            lines.append(f"modem airtime a day: {air:.0f} s at {cfg.modem.bit_rate:g} bit/s "
                         f"({costs.modem_bytes_per_hour:.0f} bytes a recording hour); {up}")
        else:
            lines.append(f"modem airtime a day: give --from RUN_DIR (a run's bytes); {up}")
    return lines


@click.command("plan")
@click.option("--config", "config_path", type=click.Path(dir_okay=False),
              help="YAML config: its schedule, power, energy and modem sections.")
@click.option("--from", "from_run", type=click.Path(file_okay=False, path_type=Path),
              help="A finished run's directory: its ledger.json's CPU per role (and modem "
                   "bytes) are an hour of recording's cost (default: the model's).")
@click.option("--date", "start", type=click.DateTime(["%Y-%m-%d"]),
              help="First UTC day planned (default: today); sunrise and sunset move.")
@click.option("--days", type=click.IntRange(1, 366), default=7, show_default=True,
              help="Days averaged over.")
def plan_command(config_path: str | None, from_run: Path | None, start: dt.datetime | None,
                 days: int) -> None:
    """Say what a schedule costs: windows and recording hours a day, Wh a day, days on the
    battery (and the modem's airtime) before the box goes in the water."""
    try:
        cfg = configmod.load(config_path)
    except TrapflowError as exc:
        raise CommandFailed(str(exc), EXIT_USAGE) from None
    costs = (costs_from_run(from_run) if from_run is not None else
             Costs(dict(RECORDING_CPU_S_PER_HOUR), None,
                   "the model's default (the gated default pipeline, docs/benchmarks.md)"))
    day = start.date() if start is not None else dt.datetime.now(dt.timezone.utc).date()
    for line in plan_lines(cfg, costs, day, days):
        click.echo(line)


COMMANDS: tuple[Any, ...] = (plan_command,)
