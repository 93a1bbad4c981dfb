"""The console tells the truth (issue 15): pairs a planned stop caught on their way are not
"lost", the status line fits 80 columns, `trapflow status` names its units, a normal end
warns of nothing, a warning every worker gives is said once, the exit summary names what
the run left, `trapflow tap` says it waits and fails when nothing came, and
`scripts/bench.sh --help` is its own help."""

from __future__ import annotations

import logging
import subprocess
import threading
import time
from pathlib import Path

import pytest
import zmq
from click.testing import CliRunner

from tests.conftest import REPO
from trapflow.cli.main import main
from trapflow.cli.status_text import POOL_UNITS, format_status
from trapflow.config.modem import OutboxConfig
from trapflow.modem.outbox import ACKED, Outbox, OutboxQueue
from trapflow.modem.port import STOPPED, LinkPort
from trapflow.runtime.node import FINALIZED, Node
from trapflow.runtime.ratelog import CONSOLE_ONCE, ConsoleOnce
from trapflow.supervisor import summary as run_summary
from trapflow.supervisor.ledger import STATUS_WIDTH, UNFINISHED, RunLedger, totals_text
from trapflow.supervisor.state import DurationClock
from trapflow.wire import tap_msgs
from trapflow.wire.messages import CaptureCounters, PoolStats, Stats


def _ledger(pools: dict[str, PoolStats], produced: int, pairs_in: int) -> RunLedger:
    led = RunLedger()
    led.on_capture(CaptureCounters(produced=produced))
    led.on_stats(Stats(t_wall_ns=0, uptime_s=1.0, pairs_in=pairs_in, rate_in=15.0, malformed=0,
                       pools=pools))
    return led


# --- unfinished at stop -------------------------------------------------------------------

def test_a_planned_stop_reports_pairs_on_their_way_as_unfinished_not_lost() -> None:
    """Regression (issue 15): every `--duration` run ended with "lost N" per pool, N the
    pairs still in the queue, at a worker or on the capture link when the stop came."""
    # 100 produced, 97 reached the broker (3 on the capture link), 5 pending, 2 in flight.
    led = _ledger({"vo": PoolStats(received=97, processed=90, pending=5, in_flight=2)}, 100, 97)
    end = led.ledger({"vo": "ordered"}, {}, planned_stop=True)["pools"]["vo"]
    assert (end["processed"], end["lost"], end[UNFINISHED]) == (90, 0, 10)
    text = totals_text(led.ledger({"vo": "ordered"}, {}, planned_stop=True))
    assert "lost 0, unfinished at stop 10," in text
    # A run that ended in failure could not finish them: lost, as before.
    failed = led.ledger({"vo": "ordered"}, {}, planned_stop=False)["pools"]["vo"]
    assert failed["lost"] == 10 and UNFINISHED not in failed


def test_what_brokers_count_lost_after_a_planned_stop_began_is_unfinished() -> None:
    """Regression (issue 15): workers stop before the broker, which then counted their pairs
    and its queue as lost ("vo: lost 15" after a plain `--duration 4`)."""
    led = _ledger({"vo": PoolStats(received=44, processed=17, lost=1, pending=20,
                                   in_flight=1)}, 44, 44)
    led.stopping()  # one pair was lost before the stop (a worker crashed)
    led.on_stats(Stats(t_wall_ns=0, uptime_s=2.0, pairs_in=44, rate_in=0.0, malformed=0,
                       pools={"vo": PoolStats(received=44, processed=18, lost=26)}))
    vo = led.ledger({"vo": "ordered"}, {}, planned_stop=True)["pools"]["vo"]
    assert (vo["processed"], vo["lost"], vo[UNFINISHED]) == (18, 1, 25)


def test_a_planned_stop_keeps_what_a_dead_broker_lost_as_lost() -> None:
    led = _ledger({"vo": PoolStats(received=60, processed=50, pending=4, in_flight=1)}, 60, 60)
    led.retire_broker()  # it held 5: they can never finish, whatever stop comes later
    led.on_stats(Stats(t_wall_ns=0, uptime_s=1.0, pairs_in=40, rate_in=15.0, malformed=0,
                       pools={"vo": PoolStats(received=40, processed=37, pending=3)}))
    led.on_capture(CaptureCounters(produced=100))
    vo = led.ledger({"vo": "ordered"}, {}, planned_stop=True)["pools"]["vo"]
    assert (vo["processed"], vo["lost"], vo[UNFINISHED]) == (87, 5, 8)
    assert vo["processed"] + vo["lost"] + vo[UNFINISHED] == 100


# --- the status line --------------------------------------------------------------------

def _pools(n: int, big: bool) -> dict[str, PoolStats]:
    k = 10**9 if big else 0
    return {f"pool{i}" if i else "mono": PoolStats(workers=1 + (i == 2) * 3, rate=14.9 + k,
                                                   dropped=k + i, errors=k, lost=k)
            for i in range(n)}


@pytest.mark.parametrize(("n_pools", "big", "up"), [
    (1, False, 3.0), (3, False, 12.0), (4, False, 86_400.0), (4, True, 86_400.0),
    (8, False, 1.0), (8, True, 10**7 * 1.0), (20, True, 10**9 * 1.0),
])
def test_the_status_line_fits_80_columns(n_pools: int, big: bool, up: float) -> None:
    """Regression (issue 15): four pools made a 170-column line that wrapped every second."""
    led = _ledger(_pools(n_pools, big), 10**12 if big else 500, 10**12 if big else 500)
    led.on_capture(CaptureCounters(produced=1, dropped=10**9 if big else 0,
                                   failures={"size": 10**9} if big else {}))
    line = led.status_text(up, {"mono": 10**6 if big else 0})
    assert len(line) <= STATUS_WIDTH, line
    left = int(line.rsplit("+", 1)[1].split()[0]) if line.endswith(" pools") else 0
    assert left < n_pools, line
    if not left:  # issue 22 item 10: every pool shown
        assert all(f" {p[:3]}" in line for p in _pools(n_pools, big)), line


def test_the_status_line_shows_every_pool_that_fits_and_flags_only_problems() -> None:
    led = _ledger({"mono": PoolStats(workers=2, rate=15.0),
                   "vo": PoolStats(workers=1, rate=14.0, dropped=3)}, 30, 30)
    line = led.status_text(5.0, {"vo": 1})
    assert line == "   5.0s | in  15.0/s (30) | mono 2w 15.0/s | vo 1w 14.0/s drop 3 rst 1"


def test_trapflow_status_names_the_unit_of_every_column() -> None:
    stats = {"pairs_in": 10, "rate_in": 2.0, "malformed": 0,
             "pools": {"vo": {k: 1 for k in POOL_UNITS}}}
    text = format_status({"run_dir": "runs/x", "uptime_s": 3.0, "nodes": [
        {"name": "capture", "pid": 1, "state": "active", "restarts": 0, "reason": ""}],
        "stats": stats})
    lines = text.splitlines()
    head = next(i for i, line in enumerate(lines) if line.startswith("pool "))
    names, units = lines[head].split(), lines[head + 1].split()
    assert names[1:] == list(POOL_UNITS) and len(units) == len(POOL_UNITS)
    assert all(u.startswith("(") and u.endswith(")") for u in units), units
    assert units[-1] == "(pairs/s)" and "(count)" in text and "pairs/s)" in text
    assert "up 3.0 s" in text


# --- no warning on a normal end; a worker's warning once ------------------------------------

class _NodeState:
    name, lifecycle, reason, _next_beat = "capture", "active", "", 1


@pytest.mark.parametrize(("reason", "normal", "level"), [
    ("source exhausted", True, logging.INFO),
    ("source failed: truncated file", False, logging.WARNING),
    ("", False, logging.INFO),
])
def test_a_planned_end_is_no_warning(caplog: pytest.LogCaptureFixture, reason: str,
                                     normal: bool, level: int) -> None:
    """Regression (issue 15): every finite run ended with `WARNING capture: finalized
    (source exhausted)` on the console."""
    caplog.set_level(logging.INFO, logger="trapflow.runtime.node")
    Node.set_state(_NodeState(), FINALIZED, reason, normal=normal)  # type: ignore[arg-type]
    assert [r.levelno for r in caplog.records] == [level]


def test_a_link_port_closed_at_a_stop_is_no_warning(caplog: pytest.LogCaptureFixture) -> None:
    """Regression (issue 15): `WARNING link port inactive: stopped` at every modem stop."""
    caplog.set_level(logging.INFO, logger="trapflow.modem.port")
    port = LinkPort("loop://")
    port.close(STOPPED)
    port.close("device unplugged")
    assert [(r.levelno, r.getMessage()) for r in caplog.records] == [
        (logging.INFO, "link port inactive: stopped"),
        (logging.WARNING, "link port inactive: device unplugged")]


def test_a_warning_every_worker_gives_reaches_the_console_once() -> None:
    """Regression (issue 15): one execution-provider warning per worker and model."""
    got: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            got.append(record.getMessage())

    handler = Keep()
    handler.addFilter(ConsoleOnce())
    log = logging.getLogger("test_console_once")
    log.addHandler(handler)
    log.propagate = False
    try:
        for _ in range(4):  # four workers
            log.warning("ONNX runs on %s", "CPU", extra={CONSOLE_ONCE: True})
        log.warning("ONNX runs on %s", "GPU", extra={CONSOLE_ONCE: True})
        log.warning("restarting %s", "vo")
        log.warning("restarting %s", "vo")  # not marked: every one is news
    finally:
        log.removeHandler(handler)
    assert got == ["ONNX runs on CPU", "ONNX runs on GPU", "restarting vo",
                   "restarting vo"]


# --- the exit summary -------------------------------------------------------------------------

def test_the_exit_summary_names_results_outbox_backlog_events_and_replayed_topics(
        tmp_path: Path) -> None:
    box = Outbox(tmp_path / "outbox.sqlite")
    seqs = box.append_many([{"mono_ir": {"seq": i}} for i in range(5)])
    box.close()
    queue = OutboxQueue(tmp_path / "outbox.sqlite", OutboxConfig())  # the modem acks two
    queue.resolve(seqs[:2], ACKED)
    assert queue.counts()[2] == 3  # the outbox's own count of what waits
    queue.close()
    for name in ("event-1", "event-2", "event-3"):
        (tmp_path / "events" / name).mkdir(parents=True)
    lines = run_summary.summary_lines(
        tmp_path / "results.jsonl", 42, tmp_path / "outbox.sqlite", tmp_path / "events",
        "replay", "/cam/left and /cam/right in rec.mcap")
    assert lines == [
        f"results: {tmp_path / 'results.jsonl'} (42 results)",
        f"outbox: {tmp_path / 'outbox.sqlite'}, 3 records still waiting for the modem",
        f"events: 3 written in {tmp_path / 'events'}",
        "replayed: /cam/left and /cam/right in rec.mcap"]
    # No outbox, events off, a live source: only the results.
    assert run_summary.summary_lines(tmp_path / "r.jsonl", 0, tmp_path / "none.sqlite", None,
                                     "synthetic", "") == [f"results: {tmp_path / 'r.jsonl'} "
                                                          "(0 results)"]


# --- trapflow tap -----------------------------------------------------------------------------

@pytest.mark.timeout(30)
def test_tap_with_no_pipeline_says_it_waits_and_fails_after_its_timeout(tmp_path: Path) -> None:
    """Regression (issue 15): `trapflow tap --timeout 5` with no pipeline printed nothing
    and exited 0."""
    t0 = time.monotonic()
    res = CliRunner().invoke(main, ["tap", "--endpoint", f"ipc://{tmp_path}/nobody",
                                    "--timeout", "1.5"])
    assert time.monotonic() - t0 >= 1.5
    assert res.exit_code == 1, res.output
    assert f"tap: waiting for a pipeline: nothing yet from ipc://{tmp_path}/nobody" in res.output
    assert res.output.splitlines()[-1].startswith(
        f"trapflow: error: tap received no message from ipc://{tmp_path}/nobody within 1.5 s")


@pytest.mark.timeout(30)
def test_tap_with_messages_exits_0_at_its_timeout(tmp_path: Path) -> None:
    ctx = zmq.Context()
    pub = ctx.socket(zmq.PUB)
    ep = f"ipc://{tmp_path}/tap"
    pub.bind(ep)
    stop = threading.Event()

    def publish() -> None:
        while not stop.is_set():
            pub.send_multipart([tap_msgs.TOPIC_RESULT, b'{"mono_ir":{"seq":1}}'])
            time.sleep(0.05)

    t = threading.Thread(target=publish, daemon=True)
    t.start()
    try:
        res = CliRunner().invoke(main, ["tap", "results", "--endpoint", ep, "--timeout", "1.5"])
    finally:
        stop.set()
        t.join(2)
        ctx.destroy(linger=0)
    assert res.exit_code == 0, res.output
    assert 'result {"mono_ir":{"seq":1}}' in res.output and "waiting" not in res.output


# --- scripts/bench.sh --help ------------------------------------------------------------------

@pytest.mark.parametrize(("args", "code", "stream", "text"), [
    (["--help"], 0, "stdout", "with their run time"),
    (["-h"], 0, "stdout",
     "Usage: scripts/bench.sh [--quick | --pi | --parts LIST] [--help] [OUT_DIR]"),
    (["--help"], 0, "stdout", "--pi: the deployment table, run on the device"),
    (["--fast"], 2, "stderr",
     "unknown option --fast (expected --quick, --pi, --parts, --help or OUT_DIR)"),
    # a part that does not exist stops before anything runs, naming the parts there are
    (["--parts", "vo,gpu"], 2, "stderr", "unknown part 'gpu' in --parts (expected some of: "
     "transport,peers,remote,shm,cpu,decode,vo,algorithms,detector,process,viewer,modem,"),
    (["--parts"], 2, "stderr", "--parts needs a list"),
])
def test_bench_sh_help_prints_its_usage_and_run_time(args: list[str], code: int, stream: str,
                                                     text: str) -> None:
    """Regression (issue 15): `scripts/bench.sh --help` printed mkdir's help and exited 2."""
    res = subprocess.run(["bash", str(REPO / "scripts" / "bench.sh"), *args],
                         capture_output=True, text=True, timeout=10)
    assert res.returncode == code, res
    assert text in getattr(res, stream), res
    assert "mkdir" not in res.stdout + res.stderr


# --- --duration ---------------------------------------------------------------------------

@pytest.mark.parametrize(("events", "stops_at"), [
    # (now, pairs produced) as the supervisor sees them; boot took 6 s before the first pair
    ([(0.0, 0), (6.0, 0), (6.1, 1), (25.0, 280), (26.0, 295), (26.1, 297)], 26.1),
    ([(0.0, 0), (0.5, 3), (20.4, 300), (20.5, 301)], 20.5),
    # a source that never sends a pair still ends, a duration after capture became active
    ([(0.0, 0), (10.0, 0), (19.9, 0), (20.0, 0)], 20.0),
])
def test_duration_counts_from_the_first_pair(events: list[tuple[float, int]],
                                              stops_at: float) -> None:
    """Regression (issue 15): `--duration 20` at 15 Hz gave 205 pairs; boot counted."""
    clock = DurationClock(20.0, active_at=0.0)
    due = [now for now, produced in events if clock.due(now, produced)]
    assert due[:1] == [stops_at]


def test_no_duration_never_ends_a_run() -> None:
    clock = DurationClock(None, active_at=0.0)
    assert not any(clock.due(t, 10) for t in (0.0, 1e6))
