"""One exit-code policy for every command (0 ok, 1 runtime failure, 2 usage or configuration),
and the pure verdict that turns a run's totals into status 1 with one line."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from trapflow.cli.main import TrapflowGroup, main
from trapflow.errors import ConfigError, ProtocolError, StartupError, TrapflowError
from trapflow.supervisor import ledger as run_totals
from trapflow.wire.messages import PoolStats, Stats


def _junk(d: Path) -> str:
    (d / "junk.mcap.part").write_bytes(b"\0" * 64)
    return str(d / "junk.mcap.part")


def _exists(d: Path) -> str:
    (d / "rec.mcap").write_bytes(b"")
    (d / "rec.mcap.part").write_bytes(b"")
    return str(d / "rec.mcap.part")


@pytest.mark.parametrize(
    ("args", "code", "error"),
    [
        (["start", "--workers", "vo=x"], 2, "expected NAME=COUNT"),
        (["start", "--config", "{d}/none.yaml", "--duration", "1"], 2, "cannot read config"),
        (["start", "--source", "nothing:x"], 2, "nothing"),
        (["replay", "{d}/missing.mcap"], 2, "recording not found"),
        (["replay", "{d}/x.mcap", "--loop", "--assert-lossless"], 2, "needs a finite replay"),
        (["replay", "{d}/x.mcap", "--workers", "vo=none"], 2, "expected NAME=COUNT"),
        (["replay", "{d}/x.mcap", "--workers", "sonar=1"], 2, "unknown algorithm 'sonar'"),
        (["replay", "{d}/x.mcap", "--size", "big"], 2, "expected WIDTHxHEIGHT"),
        (["replay", "{d}/x.mcap", "--duration", "0"], 2, "--duration"),
        (["replay", "{junk}"], 2, "not an MCAP recording"),
        (["recover", "{d}/missing.mcap.part"], 2, "cannot read"),
        (["recover", "{junk}"], 2, "not an MCAP recording"),
        (["recover", "{exists}"], 2, "exists; name another output"),
        (["status", "--run-dir", "{d}/none"], 2, "no run directory"),
        (["calibrate", "{d}/L*.png", "{d}/R*.png"], 1, "no images"),
        (["tap", "--endpoint", "ipc://{d}/nobody", "--count", "1", "--timeout", "0.2"], 1,
         "tap received no message from ipc://.*/nobody within 0.2 s"),
        (["tap", "--endpoint", "ipc://{d}/nobody", "--timeout", "0.2"], 1,
         "tap received no message"),
    ],
)
def test_every_command_follows_the_exit_code_policy(
    tmp_path: Path, args: list[str], code: int, error: str
) -> None:
    subs = {"d": str(tmp_path)}
    if any("{junk}" in a for a in args):
        subs["junk"] = _junk(tmp_path)
    if any("{exists}" in a for a in args):
        subs["exists"] = _exists(tmp_path)
    res = CliRunner().invoke(main, [a.format(**subs) for a in args])
    assert res.exit_code == code, res.output
    assert re.search(error, res.output), res.output
    if code == 1 and error:  # a runtime failure is one line that says which
        assert res.output.strip().startswith("trapflow: error: "), res.output


@pytest.mark.parametrize(
    ("error", "code"),
    [(ConfigError("bad key"), 2), (StartupError("socket in use"), 2),
     (ProtocolError("bad frame"), 1), (TrapflowError("modem gone"), 1)],
)
def test_an_error_a_command_lets_through_follows_the_policy(error: Exception, code: int) -> None:
    group = TrapflowGroup()

    @group.command()
    def boom() -> None:
        raise error

    res = CliRunner().invoke(group, ["boom"])
    assert res.exit_code == code
    assert res.output == f"trapflow: error: {error}\n"  # one line, no traceback


def _pool(**kw: Any) -> PoolStats:
    return PoolStats(workers=0, **kw)  # the final stats: every worker has stopped


def _stats(**pools: PoolStats) -> Stats:
    return Stats(t_wall_ns=0, uptime_s=1.0, pairs_in=10, rate_in=0.0, malformed=0, pools=pools)


@pytest.mark.parametrize(
    ("capture", "gave_up", "finished", "pools", "expected"),
    [
        ({"produced": 10}, None, True, {"vo": _pool(processed=10)}, []),
        # A slow pool that dropped most pairs still processed some: not a failure.
        ({"produced": 10}, None, True, {"mono": _pool(processed=1, dropped=9)}, []),
        # Stopped before anything reached the pool: nothing failed.
        ({"produced": 0}, None, False, {"vo": _pool()}, []),
        ({"produced": 40}, None, True,
         {"vo": _pool(processed=0, errors=40, failures={"WorkerError": 40}),
          "mono": _pool(processed=40)},
         ["pool vo failed every pair it was given (40: WorkerError 40); see trapflow.log"]),
        # Timed out on every pair: slow, not broken (the ledger says so); not a failure.
        ({"produced": 5}, None, True, {"slow": _pool(timed_out=5)}, []),
        ({"produced": 9}, None, True, {"vo": _pool(errors=3, timed_out=6)},
         ["pool vo failed every pair it was given (3); see trapflow.log"]),
        ({"produced": 3, "failed": 1}, "source failed: replay: x.mcap is damaged after message 7",
         True, {"vo": _pool(processed=3)},
         ["source replay could not go on: replay: x.mcap is damaged after message 7"]),
        ({"produced": 0, "failed": 3, "failed_truncated": 1, "failed_unreadable": 2}, None,
         True, {},
         ["source replay: none of its 3 pairs could be read (truncated 1, unreadable 2); "
          "see trapflow.log"]),
        # Some pairs failed at capture, the rest went through: counted, not a failed run.
        ({"produced": 7, "failed": 3, "failed_size": 3}, None, True,
         {"vo": _pool(processed=7)}, []),
    ],
)
def test_verdict(capture: dict[str, int], gave_up: str | None, finished: bool,
                 pools: dict[str, PoolStats], expected: list[str]) -> None:
    assert run_totals.verdict("replay", capture, gave_up, finished, _stats(**pools)) == expected


def test_capture_failures_by_kind() -> None:
    counters = {"produced": 4, "failed": 3, "failed_size": 1, "failed_truncated": 2,
                "failed_too_large": 0, "next_seq": 4}
    assert run_totals.capture_failures(counters) == {"size": 1, "truncated": 2}
