"""The calibrate and replay commands: exit codes, one-line errors, and replay's lossless
check (the record command's clean Ctrl-C, a real process, is in tests/integration)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import cv2
import msgspec
import numpy as np
import pytest
from click.testing import CliRunner

from trapflow.calibration.camera import StereoRig
from trapflow.cli.sources import calibrate, lossless_problems, replay
from trapflow.testing.checkerboard import render_pair
from trapflow.wire.messages import PoolStats, Stats


def test_calibrate_command_writes_yaml(tmp_path: Path) -> None:
    rig = StereoRig.from_fov(480, 360, 65.0, 0.12)
    rng = np.random.default_rng(3)
    for i in range(6):
        tvec = np.array([rng.uniform(-0.15, -0.05), rng.uniform(-0.1, -0.05), 0.6])
        left, right = render_pair(rig, (9, 6), 0.025, rng.uniform(-0.3, 0.3, 3), tvec)
        cv2.imwrite(str(tmp_path / f"l{i}.png"), left)
        cv2.imwrite(str(tmp_path / f"r{i}.png"), right)
    out = tmp_path / "calib.yaml"
    res = CliRunner().invoke(calibrate, [str(tmp_path / "l*.png"), str(tmp_path / "r*.png"),
                                         "--pattern", "9x6", "--square", "0.025", "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert "RMS reprojection error" in res.output and "views rejected (0)" in res.output
    assert "baseline_m:" in out.read_text()


@pytest.mark.parametrize(
    ("args", "code", "error"),
    [
        (["L*.png", "R*.png", "--pattern", "9by6"], 2, "expected COLSxROWS"),
        (["L*.png", "R*.png", "--square", "0"], 2, "--square"),
        (["nothing*.png", "none*.png"], 1, "no images"),
    ],
)
def test_calibrate_command_errors(args: list[str], code: int, error: str) -> None:
    res = CliRunner().invoke(calibrate, args)
    assert res.exit_code == code and error in res.output


@pytest.mark.parametrize(
    ("args", "code", "error"),
    [
        (["missing.mcap"], 2, "recording not found"),
        (["x.mcap", "--rate", "-1"], 2, "--rate"),
        (["x.mcap", "--loop", "--assert-lossless"], 2, "needs a finite replay"),
        (["x.mcap", "--option", "novalue"], 2, "expected KEY=VALUE"),
    ],
)
def test_replay_command_errors(args: list[str], code: int, error: str) -> None:
    res = CliRunner().invoke(replay, args)
    assert res.exit_code == code and error in res.output, res.output


def test_lossless_problems() -> None:
    full = PoolStats(workers=1, processed=10)
    short = PoolStats(workers=1, processed=8, dropped=2)
    off = PoolStats(workers=0)
    stats = Stats(t_wall_ns=0, uptime_s=1, pairs_in=10, rate_in=1, malformed=0,
                  pools={"mono": full, "vo": short, "tags": off})
    expected = "pool vo: processed 8 of 10 (dropped 2, failed 0, timed out 0, lost 0)"
    assert lossless_problems(10, stats, ["mono", "vo"]) == [expected]
    assert lossless_problems(12, msgspec_replace(stats, pools={"mono": full}), ["mono"])[0] \
        .startswith("read 12 pairs from the recording, 10 entered")
    assert lossless_problems(10, msgspec_replace(stats, pools={"mono": full}), ["mono"]) == []
    assert lossless_problems(10, stats, ["mono"], {"undecodable": 2, "size": 1}) == [
        "3 pairs failed at capture (size 1, undecodable 2)"]


def test_lossless_judges_every_pool_that_ran_though_its_workers_have_stopped() -> None:
    """Regression (issue 12, item 7): the final stats show 0 workers per pool, so the check
    skipped every pool and passed with 130 of 175 pairs dropped and VO failing 40 of 40."""
    stopped = Stats(t_wall_ns=0, uptime_s=9, pairs_in=175, rate_in=0, malformed=0, pools={
        "mono": PoolStats(workers=0, processed=45, dropped=130),
        "vo": PoolStats(workers=0, processed=0, errors=40, lost=135)})
    assert lossless_problems(175, stopped, ["mono", "vo"]) == [
        "pool mono: processed 45 of 175 (dropped 130, failed 0, timed out 0, lost 0)",
        "pool vo: processed 0 of 175 (dropped 0, failed 40, timed out 0, lost 135)"]
    # A pool that ran but never appears in the stats processed nothing.
    assert lossless_problems(175, stopped, ["tags"]) == [
        "pool tags: processed 0 of 175 (dropped 0, failed 0, timed out 0, lost 0)"]


def msgspec_replace(stats: Stats, **kw: object) -> Stats:
    return msgspec.structs.replace(stats, **kw)


def test_lossless_accounts_for_what_the_gate_withheld_in_a_gated_pool() -> None:
    """With --gate, a pool behind the motion gate ends a pair as processed or as gated
    (withheld by design, not lost); a pool without the gate must still process every pair,
    and a pair still kept as the gate's pre-roll has not ended."""
    stats = Stats(t_wall_ns=0, uptime_s=9, pairs_in=10, rate_in=0, malformed=0, pools={
        "mono": PoolStats(processed=4, gated=6), "vo": PoolStats(processed=10)})
    assert lossless_problems(10, stats, ["mono", "vo"], gated=["mono"]) == []
    # Without the gate asked for, gated pairs are pairs a pool did not process.
    assert lossless_problems(10, stats, ["mono", "vo"]) == [
        "pool mono: processed 4 of 10 (dropped 0, failed 0, timed out 0, lost 0)"]
    held = msgspec_replace(stats, pools={"mono": PoolStats(processed=4, gated=5, kept=1)})
    assert lossless_problems(10, held, ["mono"], gated=["mono"]) == [
        "pool mono: processed 4 of 10 (gated 5, still kept 1, dropped 0, failed 0, "
        "timed out 0, lost 0)"]


@pytest.mark.parametrize(("flags", "gates", "idle_after_s"), [
    # (replay's flags, each pool's gate, duty cycling's idle_after_s)
    ([], {"mono": "always", "stereo": "always", "vo": "always", "tags": "always"}, 0.0),
    (["--gate"], {"mono": "motion", "stereo": "motion", "vo": "always", "tags": "always"}, 30.0),
])
def test_replay_feeds_every_pair_unless_the_gate_is_asked_for(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, flags: list[str],
        gates: dict[str, str], idle_after_s: float) -> None:
    """Regression (issue 32, item 1): a replay of a default-config recording ran mono and
    stereo behind the motion gate (on by default) and --assert-lossless failed on the pairs
    it withheld. Without --gate every pool takes every pair and duty cycling is off."""
    import trapflow.supervisor.run as supervisor_run
    from trapflow.sources.replay import ReplaySource

    seen: list[Any] = []
    monkeypatch.setattr(ReplaySource, "count_pairs", lambda self: 3)
    monkeypatch.setattr(supervisor_run, "run", lambda cfg, *a, **k: seen.append(cfg)
                        or SimpleNamespace(code=0, stats=None, failure=""))
    cfg = tmp_path / "c.yaml"
    cfg.write_text("gate: {idle_after_s: 30}\n")
    res = CliRunner().invoke(replay, [str(tmp_path / "x.mcap"), "-c", str(cfg), *flags])
    assert res.exit_code == 0, res.output
    (got,) = seen
    assert {name: p.gate for name, p in got.pools.items()} == gates
    assert got.gate.idle_after_s == idle_after_s
