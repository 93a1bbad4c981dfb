"""The console's status line (trapflow.supervisor.status_line): every pool in 80 columns,
stale figures marked, and the report printing a line only when there is news."""

from __future__ import annotations

import io
from pathlib import Path

import pytest

from trapflow.config.schema import Config
from trapflow.supervisor.actions import Budget
from trapflow.supervisor.ledger import STATUS_WIDTH, RunLedger
from trapflow.supervisor.report import Report, Snapshot
from trapflow.supervisor.state import SupervisorState
from trapflow.wire.messages import CaptureCounters, PoolStats, Stats

# The pools of a busy rig, in config order; VO last, where a cut line used to lose it.
NAMES = ("mono", "stereo", "tags", "detector", "classifier", "vo")


def _ledger(pools: dict[str, PoolStats], cap: CaptureCounters | None = None) -> RunLedger:
    led = RunLedger()
    led.on_capture(cap or CaptureCounters(produced=1_000_000))
    led.on_stats(Stats(t_wall_ns=0, uptime_s=1.0, pairs_in=123_456, rate_in=15.0,
                       malformed=0, pools=pools), now=0.0)
    return led


def _pools(n: int, trouble: bool) -> dict[str, PoolStats]:
    # VO always among them: the first n-1 names and vo.
    names = [*NAMES[:n - 1], "vo"]
    return {name: PoolStats(workers=1 + i % 3, rate=14.8 - i, active=i != 2 or not trouble,
                            dropped=1234 * trouble * i, errors=12 * trouble, lost=3 * trouble)
            for i, name in enumerate(names)}


@pytest.mark.parametrize(("n_pools", "trouble", "up", "stale_s", "level"), [
    (1, False, 3.0, 0.0, ""),  # one pool: spelled out in full
    (1, True, 86_400.0, 5.0, "ir_slowed"),  # problems, a day up, stale, a ladder level
    (2, False, 12.0, 0.0, ""),
    (2, True, 3600.0, 3.0, ""),
    (3, False, 12.0, 0.0, ""),  # issue 22: one of three was behind "+1 pools"
    (3, True, 86_400.0, 9.0, "ir_slowed"),
    (4, False, 60.0, 0.0, ""),  # issue 22: with four only one showed
    (4, True, 86_400.0, 9.0, "ir_slowed"),
    (5, False, 600.0, 0.0, ""),
    (5, True, 86_400.0, 0.0, "ir_slowed"),
    (5, True, 86_400.0, 30.0, ""),
    (6, False, 999.0, 0.0, ""),
    (6, True, 86_400.0, 30.0, ""),
    (6, True, 3600.0, 0.0, "ir_slowed"),
])
def test_every_pool_shows_within_80_columns(n_pools: int, trouble: bool, up: float,
                                            stale_s: float, level: str) -> None:
    """Regression (issue 22 item 10): with 3 pools one was always behind "+1 pools" and
    which one changed mid-run; with 4 only one showed, so VO's health was invisible."""
    pools = _pools(n_pools, trouble)
    restarts = {"vo": 2} if trouble else {}
    line = _ledger(pools).status_text(up, restarts, level=level, stale_s=stale_s)
    assert len(line) <= STATUS_WIDTH, line
    assert "pools" not in line, line  # none left out
    starts = [line.find(f" {name[:3]}") for name in pools]
    assert -1 not in starts and starts == sorted(starts), line  # all of them, in order
    assert ("stale" in line) == (stale_s > 2.0), line
    if trouble:  # a problem is never hidden, however compact the line
        assert any(m in line for m in ("!", " e12", " err 12")), line


def test_the_order_of_pools_does_not_change_when_workers_do() -> None:
    """Regression (issue 22 item 10): pools were sorted by workers, so a pool that grew
    jumped ahead of the others between two lines."""
    a = _ledger({"mono": PoolStats(workers=1), "vo": PoolStats(workers=1)}).status_text(1, {})
    b = _ledger({"mono": PoolStats(workers=1), "vo": PoolStats(workers=3)}).status_text(1, {})
    assert a.index("mono") < a.index("vo") and b.index("mono") < b.index("vo")


def test_a_compact_line_abbreviates_names_and_keeps_them_apart() -> None:
    pools = {n: PoolStats(workers=2, rate=14.8) for n in
             ("stereo", "stereo_vo", "mono", "tags", "detector", "classifier")}
    line = _ledger(pools).status_text(5.0, {})
    assert len(line) <= STATUS_WIDTH and "stereo " in line and "stereo_" in line, line


@pytest.mark.parametrize(("stale_s", "stale"), [(0.0, False), (2.0, False), (2.5, True)])
def test_stats_older_than_two_seconds_are_marked(stale_s: float, stale: bool) -> None:
    """Regression (issue 22 item 10): stats that stopped coming kept their last non-zero
    rate on every line, as if still measured."""
    led = _ledger({"mono": PoolStats(workers=2, rate=14.8), "vo": PoolStats(rate=14.0)})
    line = led.status_text(9.0, {}, stale_s=stale_s)
    assert ("14.8/s?" in line and f"stale {stale_s:.0f}s" in line) == stale, line
    assert ("?" in line) == stale, line


class _Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _report(led: RunLedger, out: io.StringIO, run_dir: Path) -> Report:
    cfg = Config()
    snap = Snapshot(nodes=[], stats=led.stats, planned_stop=False, rig=None, rig_origin="",
                    source_where="", ring=None, cpu_s={})
    return Report(cfg, run_dir, out, 0.0, SupervisorState((), Budget()), led, lambda: snap)


def test_the_report_does_not_repeat_a_line_without_new_stats(tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Regression (issue 22 item 10): an unchanged line was printed every second with a
    non-zero rate; and nothing at all was printed for the first seconds of a start."""
    clock = _Clock()
    monkeypatch.setattr("trapflow.supervisor.report.time.monotonic", clock)
    led = RunLedger()
    out = io.StringIO()
    rep = _report(led, out, tmp_path)
    rep.starting(7)
    assert out.getvalue().endswith("| starting 7 processes\n")
    stats = Stats(t_wall_ns=0, uptime_s=1.0, pairs_in=10, rate_in=5.0, malformed=0,
                  pools={"vo": PoolStats(workers=1, rate=5.0)})
    led.on_stats(stats, now=clock.t)
    rep.status_line()
    clock.t += 1.0
    rep.status_line()  # no stats since: nothing new to say
    assert out.getvalue().count("vo 1w 5.0/s") == 1
    clock.t += 2.0
    rep.status_line()  # now stale: said once, marked
    rep.status_line()
    lines = out.getvalue().splitlines()
    assert len(lines) == 3 and "5.0/s?" in lines[-1] and "stale 3s" in lines[-1], lines
    led.on_stats(stats, now=clock.t)
    rep.status_line()
    assert len(out.getvalue().splitlines()) == 4
