"""Every CLI option can come from the environment (TRAPFLOW_<COMMAND>_<OPTION>), as a
systemd unit's Environment= or a container's env sets it; the command line wins."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click
import pytest
from click.testing import CliRunner

from trapflow.cli import main as cli
from trapflow.config.schema import Config
from trapflow.supervisor import run as supervisor


@pytest.fixture
def captured(monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """What `trapflow start` hands the supervisor (instead of starting processes)."""
    seen: dict[str, Any] = {}

    def fake_run(cfg: Config, run_dir: Path | None, duration: float | None,
                 **_kw: Any) -> supervisor.RunResult:
        seen.update(cfg=cfg, run_dir=run_dir, duration=duration)
        return supervisor.RunResult(0, None)

    monkeypatch.setattr(supervisor, "run", fake_run)
    return seen


def test_start_options_from_the_environment(tmp_path: Path, captured: dict[str, Any]) -> None:
    cfg_file = tmp_path / "trap.yaml"
    cfg_file.write_text("source:\n  rate_hz: 2\n")
    env = {"TRAPFLOW_START_CONFIG": str(cfg_file),
           "TRAPFLOW_START_RUN_DIR": str(tmp_path / "run"),
           "TRAPFLOW_START_WORKERS": "mono=2,vo=1",
           "TRAPFLOW_START_DURATION": "7.5",
           "TRAPFLOW_START_SIZE": "320x240",
           "TRAPFLOW_START_SEED": "11"}
    res = CliRunner().invoke(cli.main, ["start"], env=env)
    assert res.exit_code == 0, res.output
    cfg: Config = captured["cfg"]
    assert captured["run_dir"] == tmp_path / "run"
    assert captured["duration"] == 7.5
    assert cfg.source.rate_hz == 2  # from the config file the environment named
    assert (cfg.source.width, cfg.source.height, cfg.source.seed) == (320, 240, 11)
    assert {k: p.count for k, p in cfg.pools.items() if p.count} == {"mono": 2, "vo": 1}


def test_the_command_line_wins_over_the_environment(tmp_path: Path,
                                                    captured: dict[str, Any]) -> None:
    env = {"TRAPFLOW_START_RUN_DIR": str(tmp_path / "env"), "TRAPFLOW_START_RATE": "4"}
    res = CliRunner().invoke(cli.main, ["start", "--run-dir", str(tmp_path / "flag"),
                                        "--rate", "9"], env=env)
    assert res.exit_code == 0, res.output
    assert captured["run_dir"] == tmp_path / "flag"
    assert captured["cfg"].source.rate_hz == 9


@pytest.mark.parametrize(("var", "value", "expected"), [
    ("TRAPFLOW_START_RATE", "fast", "'fast'"),  # the option and the value are named
    ("TRAPFLOW_START_WORKERS", "nosuchpool=1", "nosuchpool"),
    ("TRAPFLOW_START_SIZE", "big", "big"),
])
def test_a_bad_environment_value_is_refused_by_name(var: str, value: str, expected: str,
                                                    captured: dict[str, Any]) -> None:
    res = CliRunner().invoke(cli.main, ["start"], env={var: value})
    assert res.exit_code != 0
    assert expected in res.output
    assert not captured  # nothing started


def test_status_run_dir_from_the_environment(tmp_path: Path) -> None:
    missing = tmp_path / "no-run-here"
    res = CliRunner().invoke(cli.main, ["status"], env={"TRAPFLOW_STATUS_RUN_DIR": str(missing)})
    assert res.exit_code != 0
    assert str(missing) in res.output


def _commands(group: click.Group, path: tuple[str, ...] = ()
              ) -> list[tuple[tuple[str, ...], click.Command]]:
    out: list[tuple[tuple[str, ...], click.Command]] = []
    for name, cmd in group.commands.items():
        if isinstance(cmd, click.Group):
            out += _commands(cmd, (*path, name))
        else:
            out.append(((*path, name), cmd))
    return out


@pytest.mark.parametrize(("path", "cmd"), _commands(cli.main),
                         ids=lambda v: "-".join(v) if isinstance(v, tuple) else "")
def test_every_option_reads_the_variable_named_after_its_flag(
        path: tuple[str, ...], cmd: click.Command) -> None:
    """Each option resolves TRAPFLOW_<COMMAND...>_<FLAG> from the environment, whatever
    its parameter is called in the code (--config stored as config_path included)."""
    for p in cmd.params:
        longs = [o for o in p.opts if o.startswith("--")]
        if not isinstance(p, click.Option) or not longs or p.name in ("help", "version"):
            continue
        var = "_".join(("TRAPFLOW", *path, longs[0][2:])).upper().replace("-", "_")
        ctx = click.Context(cmd, auto_envvar_prefix="_".join(("TRAPFLOW", *path)).upper())
        with pytest.MonkeyPatch.context() as mp:
            mp.setenv(var, "sentinel-value")
            assert p.resolve_envvar_value(ctx) == "sentinel-value", (var, p.name)
