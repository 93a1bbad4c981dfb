"""Plugin resolution and the command line's rejection of bad input (no processes)."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from trapflow import registry
from trapflow.cli.main import main
from trapflow.errors import WorkerError
from trapflow.plugin import Worker


@pytest.mark.parametrize("name", ["mono", "stereo", "vo", "noop", "slow", "crash"])
def test_builtin_plugins_resolve(name: str) -> None:
    assert issubclass(registry.resolve(name), Worker)


def test_import_path_resolves() -> None:
    assert registry.resolve("trapflow.testing.plugins:Noop").__name__ == "Noop"


@pytest.mark.parametrize(
    ("name", "error"),
    [
        ("sonar", "unknown algorithm 'sonar'"),
        ("no_such_module:Thing", "cannot load algorithm"),
        ("trapflow.testing.plugins:Nothing", "cannot load algorithm"),
        ("trapflow.wire.messages:Result", "is not a trapflow.plugin.Worker"),
    ],
)
def test_bad_plugins(name: str, error: str) -> None:
    with pytest.raises(WorkerError, match=error):
        registry.resolve(name)


@pytest.mark.parametrize(
    ("args", "error"),
    [
        (["start", "--workers", "mono=x"], "expected NAME=COUNT"),
        (["start", "--workers", "mono=0"], "needs workers from other hosts; set pools.mono.remote"),
        (["start", "--workers", "sonar=1", "--duration", "1"], "unknown algorithm 'sonar'"),
        (["start", "--size", "big"], "expected WIDTHxHEIGHT"),
        (["start", "--size", "4x4", "--duration", "1"], r"\$.source.width"),
        (["start", "--rate", "-3"], "-3"),
        (["start", "--duration", "0"], "0"),
        (["tap", "everything"], "'everything' is not one of"),
    ],
)
def test_cli_rejects_bad_input(args: list[str], error: str) -> None:
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 2, res.output
    assert pytest.importorskip("re").search(error, res.output), res.output


def test_cli_bad_config_file(tmp_path: Path) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text("pools:\n  mono:\n    policy: sometimes\n")
    res = CliRunner().invoke(main, ["start", "--config", str(cfg), "--duration", "1"])
    assert res.exit_code == 2
    assert "expected latest, fifo:N or ordered" in res.output
    assert "$.pools.mono" in res.output


def test_status_without_pipeline(tmp_path: Path) -> None:
    res = CliRunner().invoke(main, ["status", "--run-dir", str(tmp_path / "none")])
    assert res.exit_code == 2 and "no run directory" in res.output
