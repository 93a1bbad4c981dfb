"""Every error a user can make on the command line ends with one line on stderr
(`trapflow: error: ...`) that says what, where and the fix, and status 2 (README, "Exit
status"): click's usage errors, YAML that does not parse, a run directory not ours."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from click.testing import CliRunner

from trapflow.cli.main import main
from trapflow.config.schema import NetworkConfig
from trapflow.wire.endpoints import Endpoints

# Regression (issue 22, item 8): click printed usage, a hint, a blank line and the error (4
# lines); PyYAML's errors echoed the source (8 lines).
USAGE = [
    (["start", "--workers", "mono=x"], "trapflow start: Invalid value for '--workers'",
     "trapflow start --help"),
    (["start", "--bogus"], "trapflow start: No such option '--bogus'", "trapflow start --help"),
    (["--bogus"], "trapflow: No such option '--bogus'", "trapflow --help"),
    (["bogus"], "trapflow: No such command 'bogus'", "trapflow --help"),
    (["pool"], "trapflow pool: Missing argument 'NAME'", "trapflow pool --help"),
    (["keys", "generate"], "trapflow keys generate: Missing argument", "keys generate --help"),
]


def _one_error_line(stderr: str) -> str:
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith("trapflow: error: "), stderr
    return lines[0]


@pytest.mark.parametrize(("args", "what", "fix"), USAGE)
def test_usage_errors_are_one_line(args: list[str], what: str, fix: str) -> None:
    res = CliRunner().invoke(main, args, prog_name="trapflow")
    assert res.exit_code == 2, res.output
    line = _one_error_line(res.stderr)
    assert what in line and f"(see '{fix}" in line or fix in line, line
    assert not res.stdout


def test_a_bare_command_still_shows_its_help() -> None:
    """click asks for help with a usage error of its own: that stays help, not an error."""
    res = CliRunner().invoke(main, [], prog_name="trapflow")
    assert "Commands:" in res.output and "trapflow: error" not in res.output


@pytest.mark.parametrize(("text", "where"), [
    ("pools:\n  mono: {count: 1\n", "line 3, column 1: expected ',' or '}'"),
    ("a: b: c\n", "line 1, column 5: mapping values are not allowed here"),
    ("a: '\n", "found unexpected end of stream (while scanning a quoted scalar at line 1"),
    ("a:\tb\n\t- x\n", "line 1, column 3: found character '\\t' that cannot start any token"),
])
def test_yaml_errors_are_one_line_with_line_and_column(tmp_path: Path, text: str,
                                                       where: str) -> None:
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(text)
    res = CliRunner().invoke(main, ["start", "--config", str(cfg), "--duration", "1"],
                             prog_name="trapflow")
    assert res.exit_code == 2, res.output
    line = _one_error_line(res.stderr)
    assert f"{cfg}: not valid YAML: " in line and where in line, line


@contextlib.contextmanager
def _another_user(run_dir: Path) -> Iterator[None]:
    """Be a user who may not enter run_dir: as root, nobody (effective uid, given back at
    the end); otherwise the directory is closed to its owner too (mode 000)."""
    if os.geteuid() == 0:
        os.seteuid(65534)
        try:
            yield
        finally:
            os.seteuid(0)
    else:
        run_dir.chmod(0)
        try:
            yield
        finally:
            run_dir.chmod(0o700)


@pytest.fixture
def open_parent() -> Iterator[Path]:
    """A folder anyone may look into, as /var/lib is (pytest's own are private)."""
    d = Path(tempfile.mkdtemp(prefix="tf-"))
    d.chmod(0o755)
    yield d
    shutil.rmtree(d)


def test_status_of_a_private_run_dir_says_whose_it_is_and_what_to_do(open_parent: Path) -> None:
    """Regression (issue 22, item 8): `trapflow status --run-dir` on a systemd unit's 0700
    run directory waited 3 s and said no pipeline answered, although one was running."""
    run_dir = open_parent / "run"
    run_dir.mkdir(mode=0o700)
    sock = Endpoints.for_run(NetworkConfig(), run_dir).control.removeprefix("ipc://")
    Path(sock).write_bytes(b"")  # where a running supervisor's socket is
    with _another_user(run_dir):
        res = CliRunner().invoke(main, ["status", "--run-dir", str(run_dir)],
                                 prog_name="trapflow")
    assert res.exit_code == 2, res.output
    line = _one_error_line(res.stderr)
    owner = "root" if os.geteuid() == 0 else os.environ.get("USER", "")
    assert f"cannot reach the pipeline in {run_dir}: permission denied" in line, line
    assert f"sudo -u {owner} trapflow status --run-dir {run_dir}" in line, line
